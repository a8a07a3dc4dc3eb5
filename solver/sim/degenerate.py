"""Cases the solver must not measure, or must measure right: the honest-failure study.

Each kind spoils a simulated case the way the operating room can (docs/solver.md): the
two views taken almost from the same angle, a pin outside one view, contours too sparse to
register, 30% of the contour points outliers, or the contours of the other leg solved
against this leg's plan. The solver may answer "not_measured" with a reason, or an angle
within the tolerance of the truth; anything else is a wrong angle handed to a surgeon.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamtka.sim.simulate import SimulatedCase, SimulationConfig, simulate_case
from slamtka.solver.observations import PIN_LABELS, ViewObservation
from slamtka.solver.plan import Plan

__all__ = ["DEGENERATE_KINDS", "DegenerateCase", "degenerate_case"]

DEGENERATE_KINDS = ("views-too-close", "pin-missing", "too-few-points", "outliers", "wrong-side")

_FEW_POINTS = 15  # fewer than the 20 the study calls for, per contour
_OUTLIER_FRACTION = 0.3
_OUTLIER_REACH_PX = 60.0  # outliers scatter this far around the true contour points


@dataclass
class DegenerateCase:
    kind: str
    plan: Plan  # the plan the solver is given
    views: list[ViewObservation]
    case: SimulatedCase  # the simulation, with its truth


def _with_contours(views: list[ViewObservation], change) -> list[ViewObservation]:
    return [v.with_contours(**{label: change(k, label, pts) for label, pts in v.contours.items()})
            for k, v in enumerate(views)]


def degenerate_case(plans: dict[str, Plan], kind: str, seed: int, side: str = "right") -> DegenerateCase:
    """One spoiled case of ``kind``; ``plans`` holds the patient's plan per side (both
    sides are needed for ``wrong-side``)."""
    rng = np.random.default_rng(10_000 + seed)
    plan = plans[side]
    if kind == "views-too-close":
        first = rng.uniform(-30.0, 30.0)
        config = SimulationConfig(seed=seed, view_angles_deg=(first, first + rng.uniform(0.0, 10.0)))
        case = simulate_case(plan, config)
        return DegenerateCase(kind, plan, case.views, case)
    if kind == "wrong-side":
        other = "left" if side == "right" else "right"
        case = simulate_case(plans[other], SimulationConfig(seed=seed))
        return DegenerateCase(kind, plan, case.views, case)
    case = simulate_case(plan, SimulationConfig(seed=seed))
    if kind == "pin-missing":
        view, pin = rng.integers(len(case.views)), PIN_LABELS[rng.integers(2)]
        views = _with_contours(case.views, lambda k, label, pts:
                               pts[:0] if (k, label) == (view, pin) else pts)
    elif kind == "too-few-points":
        views = _with_contours(case.views, lambda k, label, pts:
                               pts[rng.choice(len(pts), min(_FEW_POINTS, len(pts)), replace=False)])
    elif kind == "outliers":
        def scatter(k: int, label: str, pts: np.ndarray) -> np.ndarray:
            pts = pts.copy()
            chosen = rng.random(len(pts)) < _OUTLIER_FRACTION
            pts[chosen] += rng.uniform(-_OUTLIER_REACH_PX, _OUTLIER_REACH_PX, (chosen.sum(), 2))
            return pts
        views = _with_contours(case.views, scatter)
    else:
        raise ValueError(f"unknown degenerate kind {kind!r}; choose one of {', '.join(DEGENERATE_KINDS)}")
    return DegenerateCase(kind, plan, views, case)
