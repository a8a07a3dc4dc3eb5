"""The measured angles' uncertainty: the covariance of the solved poses (with the plan's
shared segmentation error) carried to the resection angles (docs/solver.md)."""

from __future__ import annotations

import numpy as np

from slamtka.solver.measurement import angle_covariance
from slamtka.solver.optimizer import SharedError, State, Term, pose_covariance
from slamtka.solver.problem import JointProblem
from slamtka.solver.terms import BackProjectionTerm
from slamtka.solver.variables import BONE

__all__ = ["angle_uncertainty", "pin_covariance"]


def pin_covariance(problem: JointProblem, state: State, terms: list[Term], cost: float,
                   n_residuals: int) -> np.ndarray:
    """Covariance (12, 12) of the two pins' increments from the final energy ``terms`` at
    ``state``, scaled up by the fit's variance factor (``cost`` over ``n_residuals``'
    degrees of freedom) where the residuals are larger than their sigmas say."""
    fixed = problem.fixed_dofs()
    # E_mp charges the same contour pixels again that the edge points (E_rp, E_bp) explain:
    # where those exist, its information would be counted twice, and the spread understated.
    with_edges = any(term.name == "E_rp" for term in terms)
    cov_terms = [t for t in terms if not (with_edges and t.name == "E_mp")]
    cov, cov_segmentation = pose_covariance(cov_terms, state, fixed,
                                            _segmentation_error(problem, state, cov_terms))
    dof = n_residuals - len(state.points) * 3 - int(np.count_nonzero(~state.ordering.mask(fixed)))
    variance_factor = max(1.0, cost / max(dof, 1))
    return state.ordering.marginal(cov * variance_factor + cov_segmentation, problem.pin_keys)


def angle_uncertainty(problem: JointProblem, state: State, pin_cov: np.ndarray) -> np.ndarray:
    """Covariance (2, 2) rad^2 of (CTR, STR) from the pins' covariance ``pin_cov``
    (:func:`pin_covariance`)."""
    plan = problem.plan
    return angle_covariance([state.poses[key] for key in problem.pin_keys], pin_cov,
                            plan.pin_length(), plan.landmarks)


def _segmentation_error(problem: JointProblem, state: State, terms: list[Term]
                        ) -> SharedError | None:
    """The plan's bone segmentation error as an error shared by the bone's edge points
    (none for an exact mesh, or for methods without edge points).

    A segmentation error moves the surface smoothly: points on the same stretch of bone are
    off alike, which no independent per-point sigma can say (it averages away over a
    thousand points). Its covariance between two points is ``sd^2 exp(-d^2 / 2 l^2)`` for
    their distance ``d`` (``l``, ``NoiseModelConfig.segmentation_correlation_mm``), whitened by
    the bone's per-point ``sigma_mm``."""
    sd_mm = problem.plan.segmentation_sd_mm
    bone = [t for t in terms if isinstance(t, BackProjectionTerm) and t.body == BONE]
    if sd_mm <= 0.0 or not bone:
        return None
    c = problem.config
    points = state.points[np.concatenate([t.point_ids for t in bone])]
    # Points a fraction of the correlation length apart share one error (the cells'
    # centroids carry it), so that its cost grows with the bone's size, not its points'.
    cells = np.floor(points / (c.noise.segmentation_correlation_mm / 3.0)).astype(np.int64)
    _, group = np.unique(cells, axis=0, return_inverse=True)
    group = group.reshape(-1)
    counts = np.bincount(group)
    centroids = np.stack([np.bincount(group, points[:, i]) for i in range(3)], axis=1) / counts[:, None]
    squared = np.sum((centroids[:, None, :] - centroids[None, :, :]) ** 2, axis=2)
    correlation = np.exp(-squared / (2.0 * c.noise.segmentation_correlation_mm**2))
    return SharedError(list[Term](bone), group, (sd_mm / c.noise.sigma_mm) ** 2 * correlation)
