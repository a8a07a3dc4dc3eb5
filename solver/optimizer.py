"""A generic Levenberg-Marquardt optimiser over poses and 3D points (factor-graph style).

Variables are rigid poses (6 degrees of freedom each, right increments, see ``geometry``),
named by key (:mod:`.variables`), and 3D points (3 each). Energy terms are small objects
that return whitened residuals and their Jacobians for the variables they touch
(:class:`Linearization`); the optimiser knows nothing about tibias or pins. Each point
touches few poses, so points are eliminated with the Schur complement and only a small
dense system in the poses is solved: the cost of an iteration grows linearly with the
number of points. Robust losses are applied by iteratively reweighted least squares.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Protocol, runtime_checkable

import numpy as np

from slamtka.solver.geometry import Pose
from slamtka.solver.kernels import (
    coupling_blocks,
    point_blocks,
    point_steps,
    robust_cost,
    scatter_add,
    schur_complement,
    squared_norms,
)
from slamtka.solver.variables import Ordering, PoseKey

__all__ = [
    "SharedError",
    "State",
    "Linearization",
    "RobustLoss",
    "NoiseModel",
    "Term",
    "Corresponding",
    "correspond",
    "whitened",
    "LMOptions",
    "IterationInfo",
    "SolveReport",
    "levenberg_marquardt",
    "pose_covariance",
]

# Regularisation of each point's 3x3 block relative to its trace: a point whose terms leave
# a direction free (a contour point's depth along its grazing ray, unless a term holds it)
# has a rank-deficient block.
_POINT_REGULARISATION = 1e-6
# Absolute floor on the pose diagonal so an unobserved direction cannot make S singular.
_POSE_REGULARISATION = 1e-9
# The robust losses, in the order of their codes in :func:`kernels.robust_cost`.
_LOSS_KINDS = ("l2", "huber", "cauchy")


@dataclass(frozen=True)
class State:
    """All variables: the poses by key and the points (X, 3)."""

    poses: Mapping[PoseKey, Pose]
    points: np.ndarray

    @cached_property
    def ordering(self) -> Ordering:
        """Where each pose's columns sit in the system (the same for the same keys)."""
        return Ordering.of(self.poses)

    def retract(self, d_poses: np.ndarray, d_points: np.ndarray) -> State:
        """The state moved by the increments of all poses (6P,) and points (X, 3)."""
        # A held pose's increment is zero: it stays the very pose (retracting it by zero
        # would give the same values, at ~0.1 ms a pose and step).
        poses = {key: self.poses[key].retract(d) if d.any() else self.poses[key]
                 for key, d in self.ordering.split(d_poses).items()}
        return State(poses, self.points + d_points)

    def with_poses(self, poses: Mapping[PoseKey, Pose]) -> State:
        """The state with ``poses`` replacing those of their keys."""
        return State({**self.poses, **poses}, self.points)


@dataclass(frozen=True)
class RobustLoss:
    """Robust loss on the squared norm ``s`` of a whitened residual block.

    ``kind`` is ``"huber"``, ``"cauchy"`` or ``"l2"``; ``scale`` in units of sigma.
    """

    kind: str = "huber"
    scale: float = 2.0

    def __post_init__(self) -> None:
        if self.kind not in _LOSS_KINDS:
            raise ValueError(f"unknown robust loss {self.kind!r}")

    def cost(self, s: np.ndarray) -> float:
        """``sum(rho(s))`` over the squared norms ``s`` (N,) (:func:`kernels.robust_cost`)."""
        return robust_cost(s, _LOSS_KINDS.index(self.kind), float(self.scale))

    def weight(self, s: np.ndarray) -> np.ndarray:
        """IRLS weight ``rho'(s)``."""
        if self.kind == "l2":
            return np.ones_like(s)
        if self.kind == "huber":
            r = np.sqrt(s)
            return np.where(r <= self.scale, 1.0, self.scale / np.maximum(r, 1e-12))
        return 1.0 / (1.0 + s / self.scale**2)


@dataclass
class Linearization:
    """Residuals (N, m) of one term with the Jacobians of the variables they touch: in the
    term's own units as the term returns them, whitened once its :class:`NoiseModel` has
    been applied (:func:`whitened`).

    ``pose_jacobians`` holds ``(pose key, (N, m, 6))`` for each pose the term touches;
    ``point_jacobian`` holds ``(point ids (N,), (N, m, 3))``, one distinct point per residual
    block."""

    residuals: np.ndarray
    pose_jacobians: list[tuple[PoseKey, np.ndarray]] = field(default_factory=list)
    point_jacobian: tuple[np.ndarray, np.ndarray] | None = None

    @cached_property
    def squared_norms(self) -> np.ndarray:
        """(N,) squared norm of each residual block, read once whitened (the cost, the
        robust weights and the covariance share it)."""
        return squared_norms(np.ascontiguousarray(self.residuals, float))


@dataclass(frozen=True)
class NoiseModel:
    """How the optimiser charges a term's residuals: divided by ``sigma`` (one for every
    component, or one per component of a residual block), under a robust ``loss`` and
    scaled by ``weight``."""

    sigma: float | tuple[float, ...]
    loss: RobustLoss = RobustLoss("l2", 1.0)
    weight: float = 1.0

    def whiten(self, lin: Linearization) -> Linearization:
        """``lin`` in units of its sigmas, whitened in place (terms return fresh arrays).
        Per-component sigmas scale the pose Jacobians by their reciprocals, the others
        divide: the floating-point order of the terms when they whitened themselves, which
        the solver's covariance reproduces to the last bit."""
        point = None if lin.point_jacobian is None else lin.point_jacobian[1]
        if isinstance(self.sigma, tuple):
            sigma = np.asarray(self.sigma)
            lin.residuals /= sigma
            column = sigma[:, None]
            reciprocal = 1.0 / column
            for _, J in lin.pose_jacobians:
                J *= reciprocal
            if point is not None:
                point /= column
            return lin
        lin.residuals /= self.sigma
        for _, J in lin.pose_jacobians:
            J /= self.sigma
        if point is not None:
            point /= self.sigma
        return lin


class Term(Protocol):
    """One energy term: ``weight * sum(loss.rho(|r_i / sigma|^2))`` with its ``noise``;
    it returns its residuals in its own units, in arrays of its own (the optimiser
    whitens them in place)."""

    name: str
    noise: NoiseModel

    def linearize(self, state: State, jacobians: bool = True) -> Linearization: ...


def whitened(term: Term, state: State, jacobians: bool = True) -> Linearization:
    """The term's residuals (and Jacobians) at ``state`` in units of its sigmas."""
    return term.noise.whiten(term.linearize(state, jacobians))


@runtime_checkable
class Corresponding(Protocol):
    """A term whose residuals pair model and observation (a silhouette with its contour):
    it chooses the pairing at a state, and holds it until asked again."""

    def correspond(self, state: State) -> None: ...


def correspond(terms: list[Term], state: State) -> None:
    """The correspondence step at ``state``, taken before each linearisation with Jacobians
    (once per iteration): every :class:`Corresponding` term chooses its pairing there."""
    _correspond(_corresponding(terms), state)


def _corresponding(terms: list[Term]) -> list[Corresponding]:
    """The terms that take a correspondence step (a protocol check is slow: done once)."""
    return [term for term in terms if isinstance(term, Corresponding)]


def _correspond(terms: list[Corresponding], state: State) -> None:
    for term in terms:
        term.correspond(state)


@dataclass(frozen=True)
class LMOptions:
    max_iterations: int = 40
    relative_tolerance: float = 1e-6  # stop when the cost falls by less than this fraction
    step_tolerance: float = 1e-7  # ... or the pose step (rad / mm) is this small
    initial_lambda: float = 1e-3
    min_lambda: float = 1e-9
    max_lambda: float = 1e8


@dataclass
class IterationInfo:
    """What the optimiser reports after every accepted step."""

    iteration: int
    cost: float
    term_costs: dict[str, float]
    lambda_: float  # the damping the next step starts from
    state: State


@dataclass
class SolveReport:
    converged: bool
    reason: str
    iterations: int
    cost: float
    term_costs: dict[str, float]
    seconds: float
    history: list[float]


def _term_cost(term: Term, lin: Linearization) -> float:
    return term.noise.weight * term.noise.loss.cost(lin.squared_norms)


def _evaluate(terms: list[Term], state: State, jacobians: bool):
    lins = [whitened(t, state, jacobians) for t in terms]
    costs: dict[str, float] = {}
    for term, lin in zip(terms, lins):
        costs[term.name] = costs.get(term.name, 0.0) + _term_cost(term, lin)
    return lins, costs


def _scatter(keys: np.ndarray, values: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`kernels.scatter_add` of ``values``' rows, whatever their shape."""
    rows = np.ascontiguousarray(values.reshape(len(keys), int(np.prod(values.shape[1:]))))
    sums, seen = scatter_add(np.asarray(keys, np.int64), rows, n)
    return sums.reshape((n,) + values.shape[1:]), seen


def _sum_by_key(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``values`` summed over equal ``keys`` (non-negative): the distinct keys,
    sorted, and their sums (one compiled scatter-add over a dense table of the keys)."""
    if len(keys) == 0:
        return keys, values
    sums, seen = _scatter(keys, values, int(keys.max()) + 1)
    distinct = np.flatnonzero(seen)
    return distinct, sums[distinct]


def _sum_by_index(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Rows of ``values`` summed by ``index`` into ``n`` bins."""
    return _scatter(index, values, n)[0]


@dataclass
class NormalEquations:
    """Gauss-Newton system ``H d = -g`` split into pose and point blocks."""

    H_pp: np.ndarray  # (6P, 6P)
    g_p: np.ndarray  # (6P,)
    H_xx: np.ndarray  # (X, 3, 3)
    g_x: np.ndarray  # (X, 3)
    pair_point: np.ndarray  # (K,) point of each (point, pose) coupling block
    pair_pose: np.ndarray  # (K,) pose of each block
    H_px: np.ndarray  # (K, 6, 3)

    @cached_property
    def coupling(self) -> tuple[np.ndarray, np.ndarray]:
        """Each point's coupling blocks padded to a fixed count ``k``: ``W`` (X, k, 6, 3)
        and their poses ``pose_of`` (X, k), the dummy pose P filling the gaps. It does not
        depend on the damping, so the trial steps of one iteration share it."""
        P, X = len(self.g_p) // 6, len(self.H_xx)
        first = np.searchsorted(self.pair_point, np.arange(X))
        slot = np.arange(len(self.pair_point)) - first[self.pair_point]
        k_max = int(slot.max()) + 1 if len(slot) else 1
        W = np.zeros((X, k_max, 6, 3))
        pose_of = np.full((X, k_max), P)
        W[self.pair_point, slot] = self.H_px
        pose_of[self.pair_point, slot] = self.pair_pose
        return W, pose_of


def build_normal_equations(
    terms: list[Term], lins: list[Linearization], ordering: Ordering, n_points: int
) -> NormalEquations:
    P = len(ordering)
    H_blocks = np.zeros((P, P, 6, 6))
    g_blocks = np.zeros((P, 6))
    H_xx = np.zeros((n_points, 3, 3))
    g_x = np.zeros((n_points, 3))
    coupling_keys, coupling_vals = [], []
    for term, lin in zip(terms, lins):
        w = term.noise.weight * term.noise.loss.weight(lin.squared_norms)  # (N,)
        wr = (w[:, None] * lin.residuals).reshape(-1)  # (N*m,)
        sqrt_w = np.sqrt(w)[:, None, None]
        blocks = [(ordering.index(key), Ja) for key, Ja in lin.pose_jacobians]
        weighted = [(a, (sqrt_w * Ja).reshape(-1, 6)) for a, Ja in blocks]
        for a, Ja in blocks:
            g_blocks[a] += Ja.reshape(-1, 6).T @ wr
        for a, Ja_w in weighted:
            for b, Jb_w in weighted:
                H_blocks[a, b] += Ja_w.T @ Jb_w
        if lin.point_jacobian is not None:
            # Tiny blocks per residual row: compiled loops instead of batched products.
            x_idx, Jx = lin.point_jacobian
            Jx_w = point_blocks(np.ascontiguousarray(Jx, float), w, np.ascontiguousarray(lin.residuals, float),
                                np.asarray(x_idx, np.int64), H_xx, g_x)
            for a, Ja in blocks:
                coupling_keys.append(x_idx * P + a)
                coupling_vals.append(coupling_blocks(np.ascontiguousarray(Ja, float), Jx_w))
    if coupling_keys:
        # One block per (point, pose) pair, summed over the terms that couple them.
        uniq, H_px = _sum_by_key(np.concatenate(coupling_keys), np.concatenate(coupling_vals))
    else:
        uniq, H_px = np.zeros(0, np.int64), np.zeros((0, 6, 3))
    return NormalEquations(
        H_pp=H_blocks.transpose(0, 2, 1, 3).reshape(6 * P, 6 * P),
        g_p=g_blocks.reshape(-1),
        H_xx=H_xx,
        g_x=g_x,
        pair_point=uniq // P,
        pair_pose=uniq % P,
        H_px=H_px,
    )


def _reduced_system(
    ne: NormalEquations, n_poses: int, lam: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Schur complement of the LM-damped system: returns (S, rhs, V_inv).

    Damping ``lam * diag`` is applied to the pose and point blocks *before* elimination, so
    the step equals that of the damped full system."""
    P = n_poses
    H_pp = ne.H_pp + np.diag(lam * np.diag(ne.H_pp) + _POSE_REGULARISATION)
    if len(ne.H_xx) == 0:  # no points to eliminate (the silhouette stages)
        return H_pp, -ne.g_p, np.zeros((0, 3, 3))
    W, pose_of = ne.coupling
    blocks, g_shift, V_inv = schur_complement(ne.H_xx, ne.g_x, W, pose_of, P, lam,
                                              _POINT_REGULARISATION)
    S = H_pp - blocks.transpose(0, 2, 1, 3).reshape(6 * P, 6 * P)
    rhs = -ne.g_p + g_shift.reshape(-1)
    return S, rhs, V_inv


def _solve_step(ne: NormalEquations, n_poses: int, free: np.ndarray, lam: float):
    """LM step (pose increments (6P,), point increments (X, 3)) for damping ``lam``."""
    S, rhs, V_inv = _reduced_system(ne, n_poses, lam)
    S_free = S[np.ix_(free, free)]
    d_p = np.zeros(6 * n_poses)
    d_p[free] = np.linalg.solve(S_free, rhs[free])
    if len(V_inv) == 0:
        return d_p, np.zeros((0, 3))
    W, pose_of = ne.coupling
    return d_p, point_steps(W, pose_of, d_p, V_inv, ne.g_x)


def _free(ordering: Ordering, fixed_dofs: Mapping[PoseKey, np.ndarray] | None) -> np.ndarray:
    """(6P,) mask of the pose parameters that may move."""
    return ~ordering.mask(fixed_dofs or {})


def levenberg_marquardt(
    terms: list[Term],
    state: State,
    fixed_dofs: Mapping[PoseKey, np.ndarray] | None = None,
    options: LMOptions = LMOptions(),
    callback: Callable[[IterationInfo], str | None] | None = None,
) -> tuple[State, SolveReport]:
    """Minimise the robust energy of ``terms`` from ``state``.

    ``fixed_dofs`` masks, per pose key, the six parameters that must not move (gauge
    directions such as a pin's roll about its own axis). ``callback`` sees every accepted
    step; when it returns a reason (a string) the caller has what it needs (say, the
    quantity it measures has settled) and the solve ends there as converged, for that
    reason, as a Ceres iteration callback may end a solve successfully.
    """
    start = time.perf_counter()
    P, X = len(state.ordering), len(state.points)
    free = _free(state.ordering, fixed_dofs)
    corresponding = _corresponding(terms)
    _correspond(corresponding, state)
    lins, costs = _evaluate(terms, state, jacobians=True)
    cost = sum(costs.values())
    history = [cost]
    lam = options.initial_lambda
    converged, reason, iteration = False, "maximum iterations reached", 0
    for iteration in range(1, options.max_iterations + 1):
        ne = build_normal_equations(terms, lins, state.ordering, X)
        accepted = False
        while lam <= options.max_lambda:
            d_p, d_x = _solve_step(ne, P, free, lam)
            candidate = state.retract(d_p, d_x)
            cand_costs = _evaluate(terms, candidate, jacobians=False)[1]
            cand_cost = sum(cand_costs.values())
            if np.isfinite(cand_cost) and cand_cost < cost:
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            converged, reason = True, "no further decrease possible (local minimum)"
            break
        decrease = (cost - cand_cost) / max(cost, 1e-12)
        state, cost, costs = candidate, cand_cost, cand_costs
        history.append(cost)
        lam = max(lam / 10.0, options.min_lambda)
        settled = None if callback is None else callback(
            IterationInfo(iteration, cost, dict(costs), lam, state))
        if settled:
            converged, reason = True, settled
            break
        if decrease < options.relative_tolerance:
            converged, reason = True, "relative cost decrease below tolerance"
            break
        if np.max(np.abs(d_p)) < options.step_tolerance:
            converged, reason = True, "pose step below tolerance"
            break
        _correspond(corresponding, state)
        lins, costs = _evaluate(terms, state, jacobians=True)
        cost = sum(costs.values())
    return state, SolveReport(converged, reason, iteration, cost, costs,
                              time.perf_counter() - start, history)


@dataclass
class SharedError:
    """Errors shared between residuals, not estimated but considered in the covariance
    ("consider" parameters, as in navigation filters): the first residual component of the
    r-th point of ``terms`` (point terms, their rows in order) is off by the whitened error
    ``e[group[r]]``, and ``e`` has covariance ``covariance`` (G, G)."""

    terms: list[Term]
    group: np.ndarray  # (R,) in [0, G)
    covariance: np.ndarray  # (G, G)


def pose_covariance(
    terms: list[Term], state: State, fixed_dofs: Mapping[PoseKey, np.ndarray] | None = None,
    shared: SharedError | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Marginal covariance (6P, 6P) of the poses at ``state`` (points marginalised; columns
    in ``state.ordering``, :meth:`~slamtka.solver.variables.Ordering.marginal` picks poses
    by key) from independent residual noise, and the part ``shared`` adds (zero without it).

    The Schur complement of the Gauss-Newton information is exactly the marginal
    information of the poses; fixed (gauge) directions get zero variance. Residuals are
    whitened, so this is in the units of the poses' increments. A shared error ``e`` moves
    the points' gradient by ``b e`` and, through the points' coupling, the poses by
    ``A e = S^-1 (sum over coupled poses of H_px V^-1 b) e``; its covariance is
    ``A C A^T``.
    """
    P, X = len(state.ordering), len(state.points)
    correspond(terms, state)
    lins, _ = _evaluate(terms, state, jacobians=True)
    ne = build_normal_equations(terms, lins, state.ordering, X)
    S, _, V_inv = _reduced_system(ne, P, 0.0)
    free = _free(state.ordering, fixed_dofs)
    cov = np.zeros((6 * P, 6 * P))
    cov[np.ix_(free, free)] = np.linalg.pinv(S[np.ix_(free, free)], hermitian=True)
    if shared is None:
        return cov, np.zeros_like(cov)
    # b: each shared row's gradient direction on its point, robust weight included.
    by_term = {id(term): (term, lin) for term, lin in zip(terms, lins)}
    id_parts: list[np.ndarray] = []
    b_parts: list[np.ndarray] = []
    for term in shared.terms:
        term, lin = by_term[id(term)]
        x_idx, Jx = lin.point_jacobian
        w = term.noise.weight * term.noise.loss.weight(lin.squared_norms)
        id_parts.append(x_idx)
        b_parts.append(w[:, None] * Jx[:, 0, :])
    ids, b = np.concatenate(id_parts), np.concatenate(b_parts)
    W, pose_of = ne.coupling
    moved = np.einsum("rkij,rj->rki", W[ids] @ V_inv[ids][:, None], b)  # (R, k, 6)
    # Each shared error's pull on every pose: the rows' pulls summed by error and pose.
    n_errors = len(shared.covariance)
    pull = np.zeros((n_errors * (P + 1), 6))
    for slot in range(moved.shape[1]):
        pull += _sum_by_index(shared.group * (P + 1) + pose_of[ids, slot], moved[:, slot],
                              n_errors * (P + 1))
    M = pull.reshape(n_errors, P + 1, 6)[:, :P].reshape(n_errors, 6 * P).T
    A = cov @ M
    return cov, A @ shared.covariance @ A.T
