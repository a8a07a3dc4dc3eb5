"""What the quality gates read: the figures of a problem's inputs and of a solve's answer,
measured once by the solver (:func:`input_diagnostics`, :func:`diagnose`), so that the gates
(:mod:`.gates`) judge plain numbers and never reach into problems or terms."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamtka.solver.geometry import Pose, largest_angle_deg, row_norms
from slamtka.solver.measurement import (
    PinDivergence,
    pin_axis_points,
    pin_divergence,
    pins_from_anteroposterior_deg,
    plane_elevations_deg,
)
from slamtka.solver.observations import LABELS
from slamtka.solver.optimizer import RobustLoss, State, Term, whitened
from slamtka.solver.problem import InitialGuess, JointProblem
from slamtka.solver.terms import BackProjectionTerm
from slamtka.solver.variables import BONE

__all__ = ["InputDiagnostics", "OutlineFit", "PinGraze", "PinOverlap", "SolveDiagnostics",
           "StrayShare", "diagnose", "input_diagnostics", "outline_fits", "pin_overlaps",
           "residual_rms", "view_separation_deg"]


@dataclass(frozen=True)
class InputDiagnostics:
    """A problem's inputs before its solve."""

    view_ids: tuple[str, ...]
    point_counts: dict[tuple[int, str], int]  # kept contour pixels per (view index, label)
    notes: tuple[dict[str, str], ...]  # per view: extraction's note on a missing model
    view_separation_deg: float  # of the encoders' starting views


@dataclass(frozen=True)
class OutlineFit:
    """A model's silhouette traced at the solved poses against its observed contour."""

    view_id: str
    label: str
    median_px: float  # both sides: the visible outline to contour and contour to outline
    p90_px: float | None  # of the outline alone; pins with an outline only
    visible_share: float  # of the outline, where the frame could show its edge


@dataclass(frozen=True)
class StrayShare:
    """The share of a bone contour's pixels that kept no edge point (their rays miss it)."""

    view_id: str
    label: str
    fraction: float


@dataclass(frozen=True)
class PinGraze:
    """RMS distance (mm) of a pin's edge points in one view from where their rays graze it."""

    view_id: str
    label: str
    offset_mm: float


@dataclass(frozen=True)
class PinOverlap:
    """How much of one pin's shadow lies on the other's in a view: the larger share of
    either pin's projected axis within a projected radius of the other's axis."""

    view_id: str
    share: float
    # Both pins' axes lie along one image line and overlap, in a view whose pin edges the
    # fit shared out: each pin's inner end hides in the other's shadow, and nothing of the
    # extraction's split says where, so the view cannot say how far apart the pins are.
    ends_hidden: bool = False
    # In a view whose pin edges the fit shared out, the share of them off both fitted pins
    # (JointProblem.unexplained_pin_edge_share).
    unexplained_share: float = 0.0


@dataclass(frozen=True)
class SolveDiagnostics:
    """A finished solve's answer, measured; everything the answer gates need."""

    residual_rms: dict[str, float]  # whitened RMS per energy term
    n_residuals: int
    reprojection_rms_px: float | None  # E_rp's, in pixels (methods with edge points)
    stray_shares: tuple[StrayShare, ...]  # methods with edge points
    max_ray_miss_mm: float  # what made a pixel stray
    pin_grazes: tuple[PinGraze, ...]  # methods with edge points
    outlines: tuple[OutlineFit, ...]  # every model in every view
    pin_divergence: PinDivergence  # of the pins' axes from parallel, split by their plane
    # The most, over the views, of the X-ray source's elevation out of the pins' plane (deg):
    # small where every view sees that plane edge-on.
    pins_plane_elevation_deg: float
    view_separation_deg: float  # of the solved views
    pin_overlaps: tuple[PinOverlap, ...] = ()  # every view, at the solved poses
    # Where the bone contours were sought near the model's outline: per view, the share of
    # its visible outline at the solved poses along which the frame shows the bone's edge.
    sought_edge_shares: tuple[tuple[str, float], ...] = ()
    pins_from_anteroposterior_deg: float = 0.0  # the pins' mean axis from the tibia's front-to-back axis


# How close to the solved outline an edge counts as the bone's (px): the footprint's own
# rasterisation and the blur correction place a right pose's edges within 3 px (83-92% of
# the outline on simulated frames; 25% within 1 px).
SOUGHT_EDGE_REACH_PX = 3.0


def view_separation_deg(views: list[Pose]) -> float:
    """Largest angle between the viewing directions of any two views, degrees."""
    return largest_angle_deg(np.array([T.R[2] for T in views]))  # camera +z, tibia frame


def input_diagnostics(problem: JointProblem, initial: InitialGuess) -> InputDiagnostics:
    """The figures the input gate reads."""
    return InputDiagnostics(
        tuple(v.view_id for v in problem.views),
        {key: len(px) for key, px in problem.pixels.items()},
        tuple(dict(v.notes) for v in problem.views),
        view_separation_deg(list(initial.T_cam_tibia)) if problem.views else 0.0)


def residual_rms(terms: list[Term], state: State) -> tuple[dict[str, float], int]:
    """RMS over each energy term's residual rows of the row's whitened length (in units of
    its sigma: an edge point's pixel offset, its distance to the surface and along its ray,
    all six components of a relative pose at once), and the total number of residuals (for
    the degrees of freedom of the fit)."""
    sums: dict[str, list[float]] = {}
    total = 0
    for term in terms:
        r = whitened(term, state, jacobians=False).residuals
        acc = sums.setdefault(term.name, [0.0, 0])
        acc[0] += float(np.sum(r**2))
        acc[1] += r.shape[0]
        total += r.size
    return {name: float(np.sqrt(ssq / max(n, 1))) for name, (ssq, n) in sums.items()}, total


def outline_fits(problem: JointProblem, state: State, labels: tuple[str, ...]
                 ) -> tuple[OutlineFit, ...]:
    """Every model of ``labels`` in every view where it has a contour, traced at ``state``."""
    fits = []
    for term in problem.silhouette_terms(labels, 1.0, RobustLoss("l2")):
        outline, contour = term.distances_px(state)
        label = term.body.label
        median_px = float(np.median(np.concatenate([outline, contour])))
        p90_px = float(np.percentile(outline, 90)) if term.body != BONE and len(outline) else None
        fits.append(OutlineFit(problem.views[term.view.position].view_id, label, median_px, p90_px,
                               term.visible_share()))
    return tuple(fits)


def _segment_distances(p: np.ndarray, a: np.ndarray, b: np.ndarray, whole_line: bool = False
                       ) -> np.ndarray:
    """Distances of points ``p`` (N, 2) from the segment ``a``-``b`` (or its whole line)."""
    ab = b - a
    t = (p - a) @ ab / max(float(ab @ ab), 1e-12)
    if not whole_line:
        t = np.clip(t, 0.0, 1.0)
    return row_norms(p - (a + t[:, None] * ab))


def pin_overlaps(problem: JointProblem, state: State) -> tuple[PinOverlap, ...]:
    """How far the two pins' shadows lie on each other in each view at ``state``: seen one
    behind the other, a view cannot tell which contour belongs to which pin."""
    plan = problem.plan
    pins = [state.poses[key] for key in problem.pin_keys]
    radius = float(np.max(np.hypot(*np.asarray(plan.pin_mesh.vertices)[:, :2].T)))
    overlaps = []
    for k, (key, view) in enumerate(zip(problem.view_keys, problem.views)):
        in_camera = [state.poses[key].apply(pin_axis_points(T, plan.pin_length()))
                     for T in pins]
        axes = [view.camera.project(p) for p in in_camera]
        # Axes closer than a radius (pixels, at the nearer pin's depth): the shadows lie
        # more than half on each other, and neither pin shows both of its edges.
        reach = radius * view.camera.fx / min(float(np.min(p[:, 2])) for p in in_camera)
        share = max(float(np.mean(_segment_distances(axes[i], axes[j][0], axes[j][-1]) <= reach))
                    for i, j in ((0, 1), (1, 0)))
        ends_hidden = view.pin_edges is not None and share > 0 and all(
            bool(np.all(_segment_distances(axes[i], axes[j][0], axes[j][-1], whole_line=True) <= reach))
            for i, j in ((0, 1), (1, 0)))
        overlaps.append(PinOverlap(view.view_id, share, ends_hidden,
                                   problem.unexplained_pin_edge_share(k, state.poses)))
    return tuple(overlaps)


def diagnose(problem: JointProblem, state: State, terms: list[Term]) -> SolveDiagnostics:
    """The figures the answer gates read, for the final energy ``terms`` at ``state``."""
    rms, n_residuals = residual_rms(terms, state)
    seated = problem.edge_point_counts(terms)
    strays = tuple(
        StrayShare(problem.views[k].view_id, label, 1.0 - seated.get((k, label), 0) / len(pixels))
        for (k, label), pixels in problem.pixels.items()
        if seated and label == "bone" and len(pixels))
    grazes = tuple(
        PinGraze(problem.views[t.view.position].view_id, t.body.label, t.graze_offset_rms_mm(state))
        for t in terms if isinstance(t, BackProjectionTerm) and t.body in problem.pin_keys
        and t.view is not None)
    pins = [state.poses[key] for key in problem.pin_keys]
    divergence = pin_divergence(pins, problem.plan.pin_length())
    views = [state.poses[key] for key in problem.view_keys]
    elevation = max(plane_elevations_deg(pins, views, problem.plan.pin_length()))
    return SolveDiagnostics(
        rms, n_residuals,
        rms["E_rp"] * problem.config.noise.sigma_px if "E_rp" in rms else None,
        strays, problem.config.sampling.max_ray_miss_mm, grazes,
        outline_fits(problem, state, LABELS), divergence, elevation,
        view_separation_deg(views), pin_overlaps(problem, state), _sought_edge_shares(problem, state),
        pins_from_anteroposterior_deg(pins, problem.plan.landmarks))


def _sought_edge_shares(problem: JointProblem, state: State) -> tuple[tuple[str, float], ...]:
    """The frames searched again at the solved poses (:data:`SOUGHT_EDGE_REACH_PX`), where
    the bone contours were sought near the model's outline: a fit to edges found where the
    model was says little on its own."""
    if not problem.edges_sought:
        return ()
    return tuple((view.view_id, problem.bone_edges_sought(state.poses, k, SOUGHT_EDGE_REACH_PX)[1])
                 for k, view in enumerate(problem.views) if view.bone_edge_search is not None)

