"""Quality gates: why a solve's inputs or answer cannot be trusted, said in words.

Each gate returns the reason (a sentence naming the view, the model and the figure that
failed) or None. The inputs are checked before the solve (two views far enough apart, every
model seen in two of them); the answer after it (the contours fit the posed models, the pins'
edge points agree about where each pin is, the pins are the block's parallel pair, the
views moved as the encoders measured). A solve
refused by an answer gate may have lost its way; the solver then restarts it from a global
search (:func:`solver.slam.solve_joint`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from slamtka.solver.geometry import Pose
from slamtka.solver.observations import LABELS, PIN_LABELS
from slamtka.solver.optimizer import RobustLoss, State, Term
from slamtka.solver.terms import BackProjectionTerm

if TYPE_CHECKING:
    from slamtka.solver.slam import InitialGuess, JointProblem


def view_separation_deg(views: list[Pose]) -> float:
    """Largest angle between the viewing directions of any two views, degrees."""
    axes = np.array([T.R[2] for T in views])  # camera +z in the tibia frame
    cos = np.clip(axes @ axes.T, -1.0, 1.0)
    return float(np.degrees(np.max(np.arccos(cos))))


def input_refusal(problem: JointProblem, initial: InitialGuess) -> str | None:
    """Reason why these inputs cannot give a trustworthy measurement, or None."""
    c = problem.config
    if problem.n_views < 2:
        return f"only {problem.n_views} view(s); at least two are needed"
    bone_views = sum(len(problem.pixels[k, "bone"]) >= c.min_bone_points
                     for k in range(problem.n_views))
    if bone_views < 2:
        return (f"too few bone contour points: fewer than two views have at least "
                f"{c.min_bone_points}")
    for label in PIN_LABELS:
        seen = sum(len(problem.pixels[k, label]) >= c.min_pin_points
                   for k in range(problem.n_views))
        if seen < 2:
            why = "".join(f"; view {v.view_id}: {label} {v.notes[label]}"
                          for v in problem.views if label in v.notes)
            return (f"{label} is not seen in two views (needs >= {c.min_pin_points} contour "
                    f"points in each; seen in {seen}){why}")
    separation = view_separation_deg(list(initial.T_cam_tibia))
    if separation < c.min_view_separation_deg:
        return (f"views are too close in angle ({separation:.1f} deg apart; at least "
                f"{c.min_view_separation_deg:.0f} deg needed)")
    return None


def residual_rms(terms: list[Term], state: State) -> tuple[dict[str, float], int]:
    """RMS over each energy term's residual rows of the row's whitened length (in units of
    its sigma: an edge point's pixel offset, its distance to the surface and along its ray,
    all six components of a relative pose at once), and the total number of residuals (for
    the degrees of freedom of the fit)."""
    sums: dict[str, list[float]] = {}
    total = 0
    for term in terms:
        r = term.linearize(state, jacobians=False).residuals
        acc = sums.setdefault(term.name, [0.0, 0])
        acc[0] += float(np.sum(r**2))
        acc[1] += r.shape[0]
        total += r.size
    return {name: float(np.sqrt(ssq / max(n, 1))) for name, (ssq, n) in sums.items()}, total


def contour_misfit(problem: JointProblem, state: State, terms: list[Term],
                   rms: dict[str, float]) -> str | None:
    """Why the contours do not fit the posed models, or None.

    Four checks: the re-projection RMS of the edge points (methods that have them), the share
    of each bone contour's pixels whose rays miss the bone (ditto), how far each pin's edge points
    lie from where their rays graze it (ditto), and, for every model in every view,
    the median distance between its silhouette traced at the final poses and the observed
    contour. A solve caught in a wrong basin can seat its edge points well (small
    re-projection RMS) while a model's outline lies off its contour, or fit each view's pin
    contours by a pin pose that none of them quite supports."""
    c = problem.config
    if "E_rp" in rms and rms["E_rp"] * c.sigma_px > c.max_residual_rms_px:
        return (f"contours do not fit the models (re-projection RMS "
                f"{rms['E_rp'] * c.sigma_px:.1f} px > {c.max_residual_rms_px:.1f} px)")
    seated = problem.edge_point_counts(terms)
    for (k, label), pixels in problem.pixels.items():
        if not seated or label != "bone" or len(pixels) == 0:
            continue
        stray = 1.0 - seated.get((k, label), 0) / len(pixels)
        if stray > c.max_stray_fraction:
            return (f"the {label} contour of view {problem.views[k].view_id} does not fit its "
                    f"model ({100 * stray:.0f}% of its points lie more than "
                    f"{c.max_ray_miss_mm:g} mm off it > {100 * c.max_stray_fraction:.0f}%)")
    for term in terms:
        if isinstance(term, BackProjectionTerm) and term.body is not None:
            off_mm = term.graze_offset_rms_mm(state)
            if off_mm > c.max_pin_graze_offset_mm:
                label = problem.label(term.body)
                return (f"the {label} edge points of view {problem.views[term.view].view_id} "
                        f"lie off the pin ({off_mm:.2f} mm RMS from where their rays graze it "
                        f"> {c.max_pin_graze_offset_mm} mm): "
                        f"the views disagree about where it is")
    return outline_misfit(problem, state, LABELS, c.max_silhouette_median_px)


def pin_divergence(problem: JointProblem, state: State) -> str | None:
    """Why the solved pins cannot be the block's parallel pair, or None."""
    axes = [T.R[:, 2] for T in state.poses[problem.n_views:]]
    angle_deg = float(np.degrees(np.arccos(np.clip(abs(axes[0] @ axes[1]), -1.0, 1.0))))
    limit_deg = problem.config.max_pin_divergence_deg
    if angle_deg > limit_deg:
        return (f"the pins are {angle_deg:.1f} deg from parallel (> {limit_deg:g} deg): the "
                f"cutting block holds them parallel, so a pin's pose is wrong")
    return None


def odometry_misfit(rms: dict[str, float], limit_sigma: float) -> str | None:
    """Why the solved views disagree with the encoders' measured C-arm motion, or None.

    The contours of a wrong basin can be fitted by views the C-arm never moved between:
    the pins' and bone's edges then look fine while the relative pose of the views strays
    many sigmas from what the encoders measured (none when the solve had no E_odo)."""
    odo = rms.get("E_odo")
    if odo is None or odo <= limit_sigma:
        return None
    return (f"the views disagree with the encoders' C-arm motion (E_odo residual "
            f"{odo:.1f} sigma RMS > {limit_sigma:g}): a local minimum")


def outline_misfit(problem: JointProblem, state: State, labels: tuple[str, ...],
                   limit_px: float) -> str | None:
    """The first model of ``labels`` whose silhouette, traced at ``state``, lies further
    than ``limit_px`` (median, both sides) from its observed contour in some view, or, for
    a pin, a tenth of whose outline lies further than ``max_pin_outline_p90_px``, said in
    words."""
    pin_limit_px = problem.config.max_pin_outline_p90_px
    for term in problem.silhouette_terms(labels, 1.0, RobustLoss("l2")):
        outline, contour = term.distances_px(state)
        label = problem.label(term.body)
        where = f"the {label} outline in view {problem.views[term.view].view_id}"
        median_px = float(np.median(np.concatenate([outline, contour])))
        if median_px > limit_px:
            return (f"{where} does not lie on its contour (median distance {median_px:.1f} px "
                    f"> {limit_px:.1f} px)")
        if term.body is not None and len(outline):
            p90_px = float(np.percentile(outline, 90))
            if p90_px > pin_limit_px:
                return (f"{where} leaves its contour (a tenth of it lies {p90_px:.0f} px or more "
                        f"away > {pin_limit_px:.1f} px)")
    return None
