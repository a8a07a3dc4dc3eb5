"""The joint solver: both C-arm views, both pins and every edge point at once.

Problem layout (docs/solver.md, :mod:`.problem`): poses ``T_camk_tibia`` of each view and
``T_tibia_pin`` of each pin, named by key (:mod:`.variables`), and one 3D point per kept
contour pixel (bone points in the tibia frame, pin points in their pin's frame). A solve:

1. each view's bone found in its image by an exhaustive shift/rotation search;
2. the configured method's stages (:mod:`.schedule`, run by :mod:`.stages`): for the
   proposed method, silhouettes alone bringing the views and pins into the basin, then the
   joint energy ``w_rp E_rp + w_bp E_bp + w_mp E_mp (+ E_odo)`` with edge points seated on
   their rays (:mod:`.ray_seating`);
3. quality gates (:mod:`.gates`, reading :mod:`.diagnostics`), the resection plane, and its
   covariance-based uncertainty (:mod:`.uncertainty`).

A solve that went astray (stopped in the bone stage, did not converge, or whose outlines do
not fit) is run again from a global search of the patient set-up (:mod:`.setup_search`).

A pin's roll about its own axis is unobservable (a cylinder), so that direction is fixed.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np

from slamtka.solver import gates
from slamtka.solver.alignment import align_view_in_image
from slamtka.solver.diagnostics import diagnose, input_diagnostics, pin_overlaps
from slamtka.solver.gates import Why
from slamtka.solver.geometry import Pose
from slamtka.solver.measurement import ResectionPlane, fit_resection_plane, with_in_plane_sd
from slamtka.solver.observations import PIN_LABELS, ViewObservation
from slamtka.solver.optimizer import IterationInfo, SolveReport, State, Term
from slamtka.solver.pin_naming import (
    naming_clear,
    naming_score,
    pins_out_of_bone_mm,
    settle_naming,
    swap_pins,
)
from slamtka.solver.plan import Plan
from slamtka.solver.problem import InitialGuess, JointProblem, named_poses
from slamtka.solver.schedule import METHODS
from slamtka.solver.setup_search import search_setup
from slamtka.solver.solver_config import SolverConfig
from slamtka.solver.stages import StageRunner
from slamtka.solver.uncertainty import angle_uncertainty, pin_covariance
from slamtka.solver.variables import PoseKey

__all__ = ["METHODS", "InitialGuess", "SolveStart", "SolverConfig", "SolveOutcome", "solve_joint"]

log = logging.getLogger("slamtka.solver")


class SolveStart(StrEnum):
    """Where a final solve started (the result's "start", which the published schema
    lists): the encoders' guess, a global search of the patient set-up after the first
    solve went astray, or one view's solved pose with the others carried from it by the
    encoders' motion after the solve disagreed with them."""

    ENCODERS = "encoders"
    SETUP_SEARCH = "global set-up search"
    CARRIED = "carried by the encoders"


@dataclass
class SolveOutcome:
    """Everything the solve produced; ``status`` is ``measured`` or ``not_measured``."""

    status: str
    reason: str
    state: State | None
    T_cam_tibia: list[Pose]
    T_tibia_pin: list[Pose]
    plane: ResectionPlane | None
    angle_cov: np.ndarray | None  # (2, 2) rad^2 of (CTR, STR)
    residual_rms: dict[str, float]
    term_costs: dict[str, float]
    iterations: int
    seconds: float
    converged: bool
    convergence_reason: str
    point_counts: dict[str, int] = field(default_factory=dict)
    # Of those, the ones that kept an edge point in the final energy (the rest strayed off
    # the bone); empty for methods without edge points and for solves never run.
    edge_point_counts: dict[str, int] = field(default_factory=dict)
    initialisation: SolveStart = SolveStart.ENCODERS
    went_astray: bool = False  # refused because the solve lost its way, not for the geometry
    bone_edges_sought: bool = False  # the bone contours were sought near the model's outline
    why: Why | None = None  # the kind of refusal, when not measured (a stable code)
    renamed: list[str] = field(default_factory=list)  # views whose pin names were swapped
    unclear_naming: list[str] = field(default_factory=list)  # views whose pin names were open
    pins_shared: list[str] = field(default_factory=list)  # views whose pin edges the fit shared out
    # Refused because both namings of the open views were solved and neither could be told right.
    names_undecided: bool = False

    @property
    def angles_deg(self) -> tuple[float, float] | None:
        """(CTR, STR) in degrees, when a plane was fitted."""
        if self.plane is None:
            return None
        return float(np.degrees(self.plane.ctr)), float(np.degrees(self.plane.str_))


def solve_joint(
    plan: Plan,
    views: list[ViewObservation],
    initial: InitialGuess,
    config: SolverConfig = SolverConfig(),
    callback: Callable[[str, IterationInfo], None] | None = None,
) -> SolveOutcome:
    """Estimate view and pin poses jointly and measure the resection plane.

    The solve starts from the encoders' guess. If it ends in a wrong basin (the outlines do
    not fit, or it does not converge), the patient set-up error is searched for globally
    (:mod:`solver.setup_search`), over wider ranges in turn, and the solve is run again from
    there."""
    start = time.perf_counter()
    problem = JointProblem(plan, views, config)
    poses = named_poses(initial.T_cam_tibia, initial.T_tibia_pin)
    not_usable = gates.input_refusal(input_diagnostics(problem, initial), config.gates)
    if not_usable is not None:
        return _refused(problem, *not_usable, None, None, {}, start, poses)
    outcome = _solve_named(problem, initial, callback, start)
    if (outcome.why not in _PIN_REFUSALS or outcome.names_undecided or outcome.state is None
            or not problem.pins_touch(outcome.state.poses)):
        return _pins_in_the_bone(problem, outcome)
    # Refused over the pins where their shadows touch in a radiograph: the extraction's split
    # of their one bar may be what does not fit. Solved again from the views found, with the
    # bar's edges shared out by the fit (JointProblem.with_pin_edges_shared); the first
    # refusal stands unless that measures. Not where both namings were solved and neither
    # could be told right: sharing says nothing about which pin is which across views (so
    # retried, a headed-pins case refused for its names was measured 14 deg off).
    sharing = replace(problem.config, sampling=replace(problem.config.sampling, share_pin_edges=True))
    shared = _solve_named(JointProblem(plan, views, sharing), initial, callback, start,
                          named_poses(outcome.T_cam_tibia, initial.T_tibia_pin))
    log.info("pins touching in views %s: shared out by the fit, %s", shared.pins_shared, shared.status)
    chosen = shared if shared.status == "measured" else outcome
    chosen.iterations = outcome.iterations + shared.iterations
    chosen.seconds = time.perf_counter() - start
    return _pins_in_the_bone(problem, chosen)


# Refusals over how the pins fit, which the pins' shadows touching may explain.
_PIN_REFUSALS = (Why.PINS_INDISTINCT, Why.GATE_FAILED, Why.DEGENERATE)


def _solve_named(problem: JointProblem, initial: InitialGuess,
                 callback: Callable[[str, IterationInfo], None] | None, start: float,
                 poses: Mapping[PoseKey, Pose] | None = None) -> SolveOutcome:
    """A solve from ``poses`` (None: from the encoders' guess, restarting from the global
    searches while it goes astray), and, where the pins' names were left open, the solve
    under the other naming that settles them (:mod:`solver.pin_naming`)."""
    plan, views, config = problem.plan, problem.views, problem.config
    outcome = (_solve_restarting(problem, initial, callback, start) if poses is None
               else _solve_from(problem, initial, poses, callback, start))
    if not outcome.unclear_naming or (outcome.status != "measured" and not _naming_may_explain(outcome)):
        return outcome
    # The pins' names were left open by their sightings at the bone's poses. At the poses
    # solved they may be clear (a wrong naming never was on the simulated cases, where the
    # other naming met better); if not, the other naming decides by fit or by the bone
    # (solver.pin_naming), also where this one's angles came out too uncertain to report or
    # its outlines did not fit.
    unclear = outcome.unclear_naming
    named = [swap_pins(v) if v.view_id in outcome.renamed else v for v in views]
    other_views = [swap_pins(v) if v.view_id in unclear else v for v in named]
    length = plan.pin_length()
    named_mm = naming_score(named, outcome.T_cam_tibia, length)
    other_mm = naming_score(other_views, outcome.T_cam_tibia, length)
    if naming_clear(named_mm, other_mm):
        outcome.unclear_naming = []
        return outcome
    # From the views the first solve found, and without the global searches: astray, this
    # naming simply does not measure. (Going on from the first solve's bone stage instead
    # saves ~0.3 s, but measured a 20-run swapped-names study case 30 deg off: the right
    # naming failed a pin gate from there.)
    other_problem = JointProblem(plan, other_views, config, naming_fixed=True)
    other = _solve_from(other_problem, initial, named_poses(outcome.T_cam_tibia, initial.T_tibia_pin),
                        callback, start)
    chosen, refusal = settle_naming(outcome, other, unclear, sightings_prefer_second=other_mm < named_mm,
                                    out_of_bone_mm=_out_of_bone((problem, outcome), (other_problem, other)))
    log.info("views %s: pin names open; swapped they %s (%s)", unclear,
             "fit better" if chosen is other else "fit no better", other.status)
    if chosen is other:  # its names, as against the views given
        other.renamed = [v.view_id for v, given in zip(other_views, views) if v is not given]
    chosen.unclear_naming = unclear
    chosen.iterations = outcome.iterations + other.iterations
    chosen.seconds = time.perf_counter() - start  # both namings' solves
    if refusal is not None:
        chosen.status, chosen.reason, chosen.why = "not_measured", refusal, Why.PINS_INDISTINCT
        chosen.names_undecided = True
    return chosen


# Refusals of a first naming that the other naming may not share: degenerate angles (the
# wrong naming's pins cross the views' common plane) and models that do not fit (idealised
# seed 2 at level 3: the first naming's pins 2.4-3.2 px off their contours, the other's
# 0.5); which naming then stands is pin_naming.settle_naming's.
_NAMING_REFUSALS = (Why.DEGENERATE, Why.GATE_FAILED)


def _naming_may_explain(outcome: SolveOutcome) -> bool:
    """Whether the other naming of the open views may fit where this refused solve did not:
    a fit gate or too uncertain angles, or, with a bar shared out, its pins indistinct (a
    bar's edges shared out follow whatever naming the fit has: retractors seed 24's first
    shared solve, 5 deg off, left a fifth of its bar off both pins, the other naming 2.5%)."""
    return outcome.why in _NAMING_REFUSALS or (outcome.why is Why.PINS_INDISTINCT and bool(outcome.pins_shared))


# Where a view shows the pins more than this much on each other, it cannot say where each
# ends, and so how deep each is in the bone: surgeon's views seed 22 at level 3 (88% and
# 81%) had the right naming's pin 7 mm out of the bone and the wrong one's both in. The
# namings the bone settled on 23 realism cases at level 1 showed at most 62%.
_BONE_NAMING_MAX_OVERLAP = 0.75


def _out_of_bone(first: tuple[JointProblem, SolveOutcome], second: tuple[JointProblem, SolveOutcome]
                 ) -> tuple[float, float] | None:
    """How far each of the two namings' solves leaves a pin out of the bone, or None where
    the bone cannot tell for either (:func:`_pin_out_of_bone`)."""
    one, other = _pin_out_of_bone(*first), _pin_out_of_bone(*second)
    return None if one is None or other is None else (one, other)


def _pin_out_of_bone(problem: JointProblem, outcome: SolveOutcome) -> float | None:
    """How far the solve leaves a pin's deeper end out of the bone (mm, pin_naming), or None
    where the bone cannot tell: a solve without pins, or a view with the pins one behind the
    other (it cannot say how deep each is)."""
    if outcome.state is None or len(outcome.T_tibia_pin) != 2:
        return None
    if any(view.share > _BONE_NAMING_MAX_OVERLAP for view in pin_overlaps(problem, outcome.state)):
        return None
    plan = problem.plan
    return pins_out_of_bone_mm(outcome.T_tibia_pin, plan.pin_length(), plan.bone_model().sdf)


def _pins_in_the_bone(problem: JointProblem, outcome: SolveOutcome) -> SolveOutcome:
    """``outcome``, refused where it is measured with a pin that does not reach into the
    bone: the pins are drilled into the tibia, so such a pose is wrong whatever its fit
    (retractors seed 24, with a pin's outline uncharged beside a blade, a variant tried and
    not kept: its first naming passed every gate with its CTR 9.1 deg off and a pin 14 mm out
    of the bone; the naming's bone check, reached because the names were open, refused it)."""
    if outcome.status != "measured":
        return outcome
    out_of_bone = gates.pin_out_of_bone(_pin_out_of_bone(problem, outcome))
    if out_of_bone is None:
        return outcome
    # Refused as every gate refuses: no plane nor angle uncertainty goes with it (the result
    # document and the recording draw a plane wherever an outcome carries one).
    return replace(outcome, status="not_measured", reason=out_of_bone, why=Why.GATE_FAILED,
                   plane=None, angle_cov=None)


def _solve_restarting(problem: JointProblem, initial: InitialGuess,
                      callback: Callable[[str, IterationInfo], None] | None,
                      start: float) -> SolveOutcome:
    """A solve from the encoders' guess, restarted from the global set-up searches in turn
    while it goes astray. If none measures, the refusal is that of the first attempt that
    converged (its gates say what does not fit), else of the last: a restart that lost its
    way says less about the images than a solve that found the bone and failed a gate."""
    poses = named_poses(initial.T_cam_tibia, initial.T_tibia_pin)
    outcome = best = _solve_from(problem, initial, poses, callback, start)
    iterations = outcome.iterations
    observed = [(T, view.camera, view.distance_map("bone"), view.contours["bone"])
                for T, view in zip(initial.T_cam_tibia, problem.views)]
    for search in problem.config.global_searches:
        if not outcome.went_astray:
            break
        correction = search_setup(problem.bone.coarse_contour, observed,
                                  problem.plan.landmarks.T_tibia_anat(), search)
        searched = named_poses([T @ correction for T in initial.T_cam_tibia],
                               initial.T_tibia_pin)
        outcome = _solve_from(problem, initial, searched, callback, start)
        outcome.initialisation = SolveStart.SETUP_SEARCH
        iterations += outcome.iterations
        if best.why is Why.NOT_CONVERGED:
            best = outcome
    if outcome.status != "measured" and outcome.why is Why.ENCODERS_DISAGREE:
        outcome = _carried_by_the_encoders(problem, initial, outcome, callback, start)
        iterations += outcome.iterations  # of every restart it ran
    chosen = outcome if outcome.status == "measured" else best
    if (chosen.status != "measured" and chosen.why in _REFIT_REFUSALS and not problem.edges_sought
            and any(view.bone_edge_search for view in problem.views)):
        refit = _refit_on_sought_edges(problem, initial, chosen, callback, start)
        iterations += refit.iterations
        chosen = refit if refit.status == "measured" else chosen
    chosen.iterations = iterations
    return chosen


# Refusals of a solve that found the bone but whose contours may hold edges not its own:
# the posed models do not fit them, or the views they pull lie off the encoders' motion.
_REFIT_REFUSALS = (Why.GATE_FAILED, Why.ENCODERS_DISAGREE)


def _refit_on_sought_edges(problem: JointProblem, initial: InitialGuess, refused: SolveOutcome,
                           callback: Callable[[str, IterationInfo], None] | None,
                           start: float) -> SolveOutcome:
    """Solves on the bone's edges sought again near the outline that ``refused`` reached,
    ever closer (``ScheduleConfig.refit_edge_reach_px``), each from the last one's views;
    the last, with the iterations of all.

    The first contour of a frame at low dose, under scatter or processed by the C-arm holds
    edges beside the outline (a fibula's, a plateau's rim, skin lines) and misses parts of
    it; fitted to them, a solve can end a few pixels off (scatter seed 29: 9 sigma from the
    encoders; dose seed 8: its bone 2.6 px off). Near a solved outline the frame's own
    edges are the bone's (both measured within 0.15 deg), and the gates judge the new fit
    as any other: where the sought edges cover too little of the outline, it is refused."""
    outcome, iterations = refused, 0
    for reach_px in problem.config.schedule.refit_edge_reach_px:
        assert outcome.state is not None  # a fit gate's refusal and every solve keep theirs
        sought = problem.with_bone_edges_sought(outcome.state.poses, reach_px)
        outcome = _solve_from(sought, initial, named_poses(outcome.T_cam_tibia, initial.T_tibia_pin),
                              callback, start)
        outcome.initialisation = refused.initialisation
        iterations += outcome.iterations
    outcome.iterations = iterations
    log.info("edges sought again near the refused solve's outline: %s", outcome.status)
    return outcome


def _carried_by_the_encoders(problem: JointProblem, initial: InitialGuess, astray: SolveOutcome,
                             callback: Callable[[str, IterationInfo], None] | None,
                             start: float) -> SolveOutcome:
    """Solves restarted from each view of a solve the encoders contradict, the other views
    carried from it by the encoders' C-arm motion; the first that measures, else the last,
    with the iterations of all of them.

    In such a local minimum one view has usually found the bone and the other not
    (retractors seed 3: view 1 2.8 deg off, view 2 0.65 deg), and the encoders' motion,
    known to a few tenths of a degree, puts the other view near its right pose."""
    outcome, iterations = astray, 0
    for k, found in enumerate(astray.T_cam_tibia):
        carried = [T @ initial.T_cam_tibia[k].inverse() @ found for T in initial.T_cam_tibia]
        outcome = _solve_from(problem, initial, named_poses(carried, initial.T_tibia_pin), callback, start)
        outcome.initialisation = SolveStart.CARRIED
        iterations += outcome.iterations
        if outcome.status == "measured":
            break
    outcome.iterations = iterations
    return outcome


def _refused(problem: JointProblem, why: Why, reason: str, state: State | None,
             report: SolveReport | None, rms: dict[str, float], start: float,
             poses: Mapping[PoseKey, Pose] | None = None, went_astray: bool = False) -> SolveOutcome:
    """A "not_measured" outcome; ``poses`` stand in for the state when none was solved;
    ``went_astray`` says a restart from a global search may still measure."""
    final = state.poses if state is not None else poses or {}
    views = [final[key] for key in problem.view_keys if key in final]
    pins = [final[key] for key in problem.pin_keys if key in final]
    return SolveOutcome(
        "not_measured", reason, state, views, pins, None, None, rms, report.term_costs if report else {},
        report.iterations if report else 0, time.perf_counter() - start,
        bool(report and report.converged), report.reason if report else "not run",
        problem.point_counts(), went_astray=went_astray, why=why)


def _solve_from(problem: JointProblem, initial: InitialGuess, poses: Mapping[PoseKey, Pose],
                callback: Callable[[str, IterationInfo], None] | None,
                start: float) -> SolveOutcome:
    """One solve of the configured method from ``poses``, with its gates and uncertainty."""
    # Global step, shared by every method: where in each image is the bone? The views are
    # searched in parallel threads (OpenCV's template correlation releases the GIL), each
    # also building its pins' distance maps there (OpenCV's distance transform releases it
    # too: 10-20 ms each, which the later stages would otherwise build one after another).
    def aligned(T: Pose, view: ViewObservation) -> Pose:
        for label in PIN_LABELS:
            view.distance_map(label)
        return align_view_in_image(problem.bone.contour, T, view.camera, view.distance_map("bone"))

    with ThreadPoolExecutor(len(problem.views)) as pool:
        views = pool.map(aligned, [poses[key] for key in problem.view_keys], problem.views)
        poses = {**poses, **dict(zip(problem.view_keys, views))}
    runner = StageRunner(problem, initial, callback)
    result = runner.run(State(poses, np.zeros((0, 3))))
    fine = result.report
    report = SolveReport(fine.converged, fine.reason, runner.iterations, fine.cost,
                         fine.term_costs, runner.seconds, fine.history)
    attributed = runner.problem  # with the foreign edges dropped
    outcome = _judged(attributed, result.state, result.terms, fine, report, start)
    # The contour points offered (as extracted), and those that kept an edge point.
    outcome.point_counts = problem.point_counts()
    outcome.edge_point_counts = attributed.named(attributed.edge_point_counts(result.terms))
    outcome.bone_edges_sought = attributed.edges_sought
    outcome.renamed, outcome.unclear_naming = runner.renamed, runner.unclear_naming
    outcome.pins_shared = runner.pins_shared
    return outcome


def _judged(problem: JointProblem, state: State, terms: list[Term], fine: SolveReport,
            report: SolveReport, start: float) -> SolveOutcome:
    """The outcome of a finished solve: its quality gates, then the plane and its
    covariance-based uncertainty."""
    limits, plan = problem.config.gates, problem.plan
    d = diagnose(problem, state, terms)
    rms = d.residual_rms
    if not fine.converged:
        return _refused(problem, Why.NOT_CONVERGED, f"the solve did not converge ({fine.reason})",
                        state, report, rms, start, went_astray=True)
    hidden = gates.hidden_outline(d, limits)
    if hidden is not None:
        return _refused(problem, Why.BONE_OUTLINE_INSUFFICIENT, hidden, state, report, rms, start)
    pins = [state.poses[key] for key in problem.pin_keys]
    pin_cov: np.ndarray | None = None
    if d.pin_divergence.total > limits.max_pin_divergence_deg >= d.pin_divergence.out_of_plane:
        # Too far from parallel within the pins' plane: does the fit resolve that turn?
        pin_cov = pin_covariance(problem, state, terms, fine.cost, d.n_residuals)
        d = replace(d, pin_divergence=with_in_plane_sd(d.pin_divergence, pins, pin_cov, plan.pin_length()))
    for gate, why in ((gates.contour_misfit, Why.GATE_FAILED), (gates.sought_edges_missing, Why.GATE_FAILED),
                      (gates.pin_divergence, Why.GATE_FAILED), (gates.odometry_misfit, Why.ENCODERS_DISAGREE)):
        misfit = gate(d, limits)
        if misfit is None:
            continue
        # Where the pins' shadows lie on each other, that is why they do not fit (unless a
        # restart finds poses where they do).
        overlapping = gates.pins_overlap(d, limits) if why is Why.GATE_FAILED else None
        if overlapping is not None:
            why, misfit = Why.PINS_INDISTINCT, f"{overlapping} ({misfit})"
        return _refused(problem, why, misfit, state, report, rms, start, went_astray=True)
    indistinct = gates.pins_in_line(d) or gates.shared_bar_unexplained(d, limits)
    if indistinct is not None:
        return _refused(problem, Why.PINS_INDISTINCT, indistinct, state, report, rms, start)
    across = gates.pins_across_the_tibia(d, limits)
    if across is not None:
        return _refused(problem, Why.GATE_FAILED, across, state, report, rms, start)
    too_close = gates.view_separation(d, limits)
    if too_close is not None:
        return _refused(problem, Why.VIEWS_TOO_CLOSE, too_close, state, report, rms, start)

    final_views = [state.poses[key] for key in problem.view_keys]
    plane = fit_resection_plane(pins, plan.pin_length(), plan.landmarks)
    if pin_cov is None:
        pin_cov = pin_covariance(problem, state, terms, fine.cost, d.n_residuals)
    angle_cov = angle_uncertainty(problem, state, pin_cov)
    sigma_deg = np.degrees(np.sqrt(np.diag(angle_cov)))
    outcome = SolveOutcome("measured", "", state, final_views, pins, plane, angle_cov, rms,
                           fine.term_costs, report.iterations, time.perf_counter() - start,
                           True, fine.reason, problem.point_counts())
    degenerate = gates.angle_uncertainty(float(np.max(sigma_deg)), limits)
    if degenerate is not None:
        outcome.status, outcome.reason, outcome.why = "not_measured", degenerate, Why.DEGENERATE
    return outcome
