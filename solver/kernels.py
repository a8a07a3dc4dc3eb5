"""Compiled (numba) kernels for per-point loops that numpy expresses only as many small
batched products.

The Schur complement of an iteration eliminates each edge point's 3x3 block and folds its
one or two (6, 3) couplings into the pose blocks: with numpy that is a dozen passes over
(X, k, 6, 6) temporaries and sparse sums per trial step (a third of the joint stages'
time); one compiled pass over the points does the same arithmetic in registers.
Compiled on first use and cached beside this file when it is writable (the service's
warm-up pays the first compilation, about a second).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["schur_complement", "warm_up"]


@numba.njit(cache=True, nogil=True)
def _inverse_3x3(M: np.ndarray, out: np.ndarray) -> None:
    """``out`` = inverse of the 3x3 ``M`` from its cofactors (as the numpy path does)."""
    c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    c01 = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
    c02 = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
    det = M[0, 0] * c00 + M[0, 1] * c01 + M[0, 2] * c02
    out[0, 0] = c00 / det
    out[1, 0] = c01 / det
    out[2, 0] = c02 / det
    out[0, 1] = (M[2, 1] * M[0, 2] - M[2, 2] * M[0, 1]) / det
    out[1, 1] = (M[2, 2] * M[0, 0] - M[2, 0] * M[0, 2]) / det
    out[2, 1] = (M[2, 0] * M[0, 1] - M[2, 1] * M[0, 0]) / det
    out[0, 2] = (M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]) / det
    out[1, 2] = (M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]) / det
    out[2, 2] = (M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]) / det


@numba.njit(cache=True, nogil=True)
def schur_complement(H_xx: np.ndarray, g_x: np.ndarray, W: np.ndarray, pose_of: np.ndarray,
                     n_poses: int, lam: float, regularisation: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point ``x``: its block damped (``lam`` times its diagonal, plus
    ``regularisation`` times its trace) and inverted, ``V_inv`` (X, 3, 3); the sums over
    points of ``W_a V_inv W_b^T`` into the pose-pair blocks (P, P, 6, 6) and of
    ``W_a V_inv g_x`` into each pose (P, 6). ``W`` (X, k, 6, 3) holds each point's
    couplings, ``pose_of`` (X, k) their poses (``n_poses`` marks an empty slot)."""
    X, k = pose_of.shape
    blocks = np.zeros((n_poses, n_poses, 6, 6))
    shift = np.zeros((n_poses, 6))
    V_inv = np.empty((X, 3, 3))
    V = np.empty((3, 3))
    Y = np.empty((k, 6, 3))
    for x in range(X):
        trace = H_xx[x, 0, 0] + H_xx[x, 1, 1] + H_xx[x, 2, 2]
        reg = regularisation * max(trace, 1e-9)
        for i in range(3):
            for j in range(3):
                V[i, j] = H_xx[x, i, j]
            V[i, i] += lam * H_xx[x, i, i] + reg
        _inverse_3x3(V, V_inv[x])
        for a in range(k):
            pa = pose_of[x, a]
            if pa >= n_poses:
                continue
            for r in range(6):
                for j in range(3):
                    Y[a, r, j] = (W[x, a, r, 0] * V_inv[x, 0, j] + W[x, a, r, 1] * V_inv[x, 1, j]
                                  + W[x, a, r, 2] * V_inv[x, 2, j])
                shift[pa, r] += Y[a, r, 0] * g_x[x, 0] + Y[a, r, 1] * g_x[x, 1] + Y[a, r, 2] * g_x[x, 2]
            for b in range(k):
                pb = pose_of[x, b]
                if pb >= n_poses:
                    continue
                for r in range(6):
                    for c in range(6):
                        blocks[pa, pb, r, c] += (Y[a, r, 0] * W[x, b, c, 0] + Y[a, r, 1] * W[x, b, c, 1]
                                                 + Y[a, r, 2] * W[x, b, c, 2])
    return blocks, shift, V_inv


def warm_up() -> None:
    """Compile (or load from the cache) every kernel now, on a tiny problem: the first
    compilation takes about two seconds, which no case in the operating room should wait."""
    schur_complement(np.eye(3)[None], np.zeros((1, 3)), np.zeros((1, 1, 6, 3)),
                     np.zeros((1, 1), np.int64), 1, 0.0, 1e-6)
