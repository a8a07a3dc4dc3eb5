"""Bundle adjustment of a ball-plate calibration: intrinsics, distortion, plate poses, plate.

One focal length (the pixel aspect fixed by the detector's spacing), the principal point,
the image-intensifier distortion (:mod:`solver.imaging.distortion`, centred on the field),
every frame's plate pose and, optionally, the plate itself: each ball's offset from the
perfect grid (a real plate's manufacturing error, about 0.15 mm RMS).

A plate seen only in images is known up to a similarity (shift, rotation, scale), which the
poses absorb: the offsets are expressed in a basis orthogonal to those seven modes
(linearised at the grid), so the pitch is a pure scale that changes no intrinsic. Everything
else, a shear or a bend of the plate included, the tilted views determine (with the plate
taken as perfect such errors would leak into the focal length and principal point); a weak
prior keeps balls seen in few frames in place.

The loss is robust (Huber), and observations far off the fit (a speck taken for a ball) are
removed by the caller between solves (:func:`ball_residuals`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from slamtka.solver.imaging.distortion import Distortion

__all__ = ["Bundle", "Observations", "rotations", "plate_basis", "solve", "ball_residuals",
           "parameter_sigmas", "N_INTRINSIC"]

N_INTRINSIC = 7  # f, cx, cy, k1, k2, t1, t2
_PRIOR_PLATE_MM = 0.5  # the prior's SD of a ball's offset from the grid
_PRIOR_PX = 0.05  # the pixel scale the prior is weighed against (weak: the data decide)


@dataclass
class Observations:
    """Every ball seen: its frame (index), its ball on the plate (index), its pixel position."""

    frame: np.ndarray  # (M,) int
    ball: np.ndarray  # (M,) int, row * cols + col
    uv: np.ndarray  # (M, 2)
    active: np.ndarray  # (M,) bool: not (yet) an outlier


def rotations(rvecs: np.ndarray) -> np.ndarray:
    """Rotation matrices (K, 3, 3) of rotation vectors (K, 3) (Rodrigues, vectorised)."""
    theta = np.linalg.norm(rvecs, axis=1)
    k = rvecs / np.where(theta > 1e-12, theta, 1.0)[:, None]
    K = np.zeros((len(rvecs), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K -= K.transpose(0, 2, 1)
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def plate_basis(nominal: np.ndarray) -> np.ndarray:
    """Orthonormal basis (3N, 3N - 7) of ball offsets that are not a similarity of the plate.

    Removed (linearised at the grid ``nominal`` (N, 3), z = 0): shifts (3), rotations (3)
    and the scale (1), which the poses absorb; so the pitch changes no intrinsic.
    """
    x, y = nominal[:, 0], nominal[:, 1]
    zero, one = np.zeros(len(nominal)), np.ones(len(nominal))
    modes = [(one, zero, zero), (zero, one, zero), (zero, zero, one),  # shifts
             (-y, x, zero), (zero, zero, y), (zero, zero, -x),  # rotations about z, x, y
             (x, y, zero)]  # scale
    A = np.column_stack([np.column_stack(m).ravel() for m in modes])
    q, _ = np.linalg.qr(A, mode="complete")
    return q[:, A.shape[1]:]


@dataclass
class Bundle:
    """The model: nominal plate, its offset basis (None: the plate is taken as perfect),
    the distortion's fixed centre and radius, and the pixel aspect (fy / fx)."""

    nominal: np.ndarray  # (N, 3) mm
    basis: np.ndarray | None  # (3N, m)
    base: Distortion
    aspect: float
    frames: int

    @property
    def size(self) -> int:
        return N_INTRINSIC + 6 * self.frames + (0 if self.basis is None else self.basis.shape[1])

    def plate(self, x: np.ndarray) -> np.ndarray:
        """Ball centres (N, 3) mm of the parameter vector ``x``."""
        if self.basis is None:
            return self.nominal
        return self.nominal + (self.basis @ x[N_INTRINSIC + 6 * self.frames:]).reshape(-1, 3)

    def poses(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = x[N_INTRINSIC: N_INTRINSIC + 6 * self.frames].reshape(-1, 6)
        return rotations(p[:, :3]), p[:, 3:]

    def project(self, x: np.ndarray, frame: np.ndarray, ball: np.ndarray) -> np.ndarray:
        """Pixels (M, 2) where ball ``ball[i]`` appears in frame ``frame[i]``."""
        f, cx, cy = x[:3]
        R, t = self.poses(x)
        p = np.einsum("mij,mj->mi", R[frame], self.plate(x)[ball]) + t[frame]
        uv = np.column_stack([f * p[:, 0] / p[:, 2] + cx, f * self.aspect * p[:, 1] / p[:, 2] + cy])
        return self.base.distort_with(x[3:7], uv)

    def residuals(self, x: np.ndarray, obs: Observations) -> np.ndarray:
        a = obs.active
        r = (self.project(x, obs.frame[a], obs.ball[a]) - obs.uv[a]).ravel()
        if self.basis is None:
            return r
        return np.concatenate([r, x[N_INTRINSIC + 6 * self.frames:] * (_PRIOR_PX / _PRIOR_PLATE_MM)])


def solve(bundle: Bundle, x0: np.ndarray, obs: Observations, lower: np.ndarray, upper: np.ndarray,
          free: np.ndarray | None = None, robust_px: float | None = 1.0):
    """Least squares over the ``free`` parameters (default: all); Huber loss beyond
    ``robust_px`` (None: plain squares). Returns (x, scipy result)."""
    free = np.ones(len(x0), bool) if free is None else free
    x = x0.copy()

    def fun(y: np.ndarray) -> np.ndarray:
        full = x.copy()
        full[free] = y
        return bundle.residuals(full, obs)

    result = least_squares(fun, x0[free], bounds=(lower[free], upper[free]), x_scale="jac",
                           method="trf", loss="linear" if robust_px is None else "huber",
                           f_scale=robust_px or 1.0)
    x[free] = result.x
    return x, result


def ball_residuals(bundle: Bundle, x: np.ndarray, obs: Observations) -> np.ndarray:
    """Reprojection error (px) of every observation, outliers included."""
    return np.linalg.norm(bundle.project(x, obs.frame, obs.ball) - obs.uv, axis=1)


def parameter_sigmas(result, observations: int) -> np.ndarray:
    """Standard deviations of the solved parameters (from J^T J and the residual variance);
    infinite where the set does not determine them."""
    J = result.jac
    dof = max(1, observations - J.shape[1])
    sigma2 = float(result.fun @ result.fun) / dof
    try:
        cov = np.linalg.inv(J.T @ J) * sigma2
    except np.linalg.LinAlgError:
        return np.full(J.shape[1], np.inf)
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))
