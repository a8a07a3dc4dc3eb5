"""Runs a method's stage table (:mod:`.schedule`) on a shared state: the optimiser stages,
with the steps between them (pin triangulation, edge-point seating, the bone stage's checks).

Every method starts from the same global image alignment and triangulates the pins from
their contours once the views are known, so the methods differ only in their energy and in
what is estimated when."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from slamtka.solver import gates
from slamtka.solver.diagnostics import OutlineFit, outline_fits
from slamtka.solver.measurement import fit_resection_plane
from slamtka.solver.observations import PIN_LABELS
from slamtka.solver.optimizer import (
    IterationInfo,
    LMOptions,
    RobustLoss,
    SolveReport,
    State,
    Term,
    correspond,
    levenberg_marquardt,
)
from slamtka.solver.problem import InitialGuess, JointProblem
from slamtka.solver.schedule import SCHEDULES, Held, Stage, Step
from slamtka.solver.variables import PoseKey

__all__ = ["StageRunner", "StagesResult"]

log = logging.getLogger("slamtka.solver")


class _SettledAngles:
    """Iteration callback that ends a stage once an accepted step moved neither resection
    angle (CTR, STR) by more than ``ScheduleConfig.settled_angle_deg``."""

    def __init__(self, problem: JointProblem, state: State):
        self.problem = problem
        self.angles = self._angles(state)

    def _angles(self, state: State) -> np.ndarray:
        plan = self.problem.plan
        plane = fit_resection_plane([state.poses[key] for key in self.problem.pin_keys],
                                    plan.pin_length(), plan.landmarks)
        return np.degrees([plane.ctr, plane.str_])

    def __call__(self, info: IterationInfo) -> str | None:
        angles = self._angles(info.state)
        moved = float(np.max(np.abs(angles - self.angles)))
        self.angles = angles
        limit = self.problem.config.schedule.settled_angle_deg
        if moved > limit:
            return None
        return f"resection angles settled (moved {moved:.4f} <= {limit} deg)"


@dataclass
class StagesResult:
    """The final state, the terms of the final energy (for the covariance and residuals)
    and the report of the last optimiser stage."""

    state: State
    terms: list[Term]
    report: SolveReport


class StageRunner:
    """The stages of the configured method, run one after another; ``problem`` is replaced
    as the bone stage drops foreign edges and matches pin labels."""

    def __init__(self, problem: JointProblem, initial: InitialGuess,
                 callback: Callable[[str, IterationInfo], None] | None):
        self.problem, self.callback, self.initial = problem, callback, initial
        self.schedule = SCHEDULES[problem.config.method]
        self.odometry = problem.odometry_terms(initial) if self.schedule.odometry else []
        self.iterations, self.seconds = 0, 0.0
        self.renamed: list[str] = []  # views whose pin names were swapped
        self.unclear_naming: list[str] = []  # views whose pin names the sightings leave open
        self.pins_shared: list[str] = []  # views whose pin edges the fit shares out

    def lm(self, terms: list[Term], state: State, held: dict[PoseKey, np.ndarray], options: LMOptions,
           name: str, until_settled: bool = False) -> tuple[State, SolveReport]:
        """One optimiser stage; with ``until_settled`` it also ends once the resection
        angles stop moving (:class:`_SettledAngles`)."""
        settled = _SettledAngles(self.problem, state) if until_settled else None

        def stage(info: IterationInfo) -> str | None:
            if self.callback is not None:
                self.callback(name, info)
            return None if settled is None else settled(info)

        state, report = levenberg_marquardt(terms, state, held, options, stage)
        self.iterations += report.iterations
        self.seconds += report.seconds
        return state, report

    def run(self, state: State) -> StagesResult:
        """Every stage of the method's table in order (:mod:`.schedule`)."""
        result = StagesResult(state, [], SolveReport(False, "not run", 0, 0.0, {}, 0.0, []))
        for stage in self.schedule.stages:
            if stage.step is Step.BONE_SILHOUETTE:
                result, stopped = self._bone(stage, result)
                if stopped:
                    return result
            elif stage.step is Step.TRIANGULATE_PINS:
                pins = self.problem.triangulated_pins(result.state.poses)
                result = StagesResult(result.state.with_poses(pins), result.terms, result.report)
            elif stage.step is Step.SILHOUETTES:
                result = self._silhouettes(stage, result)
            elif stage.step is Step.EDGES:
                result = self._edges(stage, result)
            else:
                result = self._joint(stage, result)
        return result

    def _held(self, stage: Stage) -> dict[PoseKey, np.ndarray]:
        return self.problem.fixed_dofs(views=stage.held is Held.VIEWS, pins=stage.held is Held.PINS)

    def _options(self, stage: Stage) -> LMOptions:
        assert stage.budget is not None
        options: LMOptions = getattr(self.problem.config.schedule, stage.budget)
        return options

    def _odometry(self, stage: Stage) -> list[Term]:
        return self.odometry if stage.odometry else []

    def _tight(self) -> RobustLoss:
        return RobustLoss("cauchy", self.problem.config.schedule.coarse_loss_scales[-1])

    def _bone(self, stage: Stage, result: StagesResult) -> tuple[StagesResult, bool]:
        """Views on the bone's silhouette, with a robust scale shrinking from wide to tight;
        then the checks that need the views on the bone. True when the solve stops here.

        Where the bone still lies off its contour, its edges are sought near the model's
        outline (:meth:`_bone_edges_sought`): from the aligned poses first (foreign edges in
        a poor contour, a femur's or a retractor's, may have pulled a view further off than
        the alignment left it), then from the poses the fit reached, each time with the
        views that still lie off carried from the best-fitting one by the encoders' motion
        (:meth:`_carried`)."""
        p, c = self.problem, self.problem.config
        original, aligned = p, result.state
        state = result.state
        for scale in c.schedule.coarse_loss_scales:
            terms = p.silhouette_terms(stage.labels, 1.0, RobustLoss("cauchy", scale),
                                       light=scale >= c.schedule.light_mesh_min_scale,
                                       thinned=stage.thinned)
            state, _ = self.lm(terms + self._odometry(stage), state, self._held(stage),
                               self._options(stage), f"{stage.name} x{scale:g}")
        p, fits, astray = self._judged_bone(stage, state)
        fitted = state
        if astray is not None and any(view.bone_edge_search for view in p.views):
            for start in (aligned, fitted):
                if start is aligned:  # the edges the views dropped there may be the bone's
                    self.problem = original
                state = self._bone_edges_sought(stage, start)
                p, fits, astray = self._judged_bone(stage, state)
                carried = self._carried(state, fits) if astray is not None else None
                if carried is not None:
                    self.problem = original
                    state = self._bone_edges_sought(stage, carried)
                    p, fits, astray = self._judged_bone(stage, state)
                if astray is None:
                    break
        if astray is not None:
            # Lost already: the caller may restart from a global search at once.
            final = list[Term](p.silhouette_terms(stage.labels, 1.0, self._tight()))
            correspond(final, state)
            return StagesResult(state, final, SolveReport(
                False, f"{astray} after the bone stage", self.iterations, 0.0, {}, self.seconds, [])), True
        p, self.renamed, self.unclear_naming = p.relabelled(state.poses)
        self.problem = p
        for view_id in self.renamed:
            log.info("view %s: the pin labels were swapped to match the other views", view_id)
        return StagesResult(state, result.terms, result.report), False

    def _judged_bone(self, stage: Stage, state: State
                     ) -> tuple[JointProblem, tuple[OutlineFit, ...], str | None]:
        """The problem without the foreign edges the views on the bone show, the bone's
        outline fits, and why the bone still lies off its contour in some view (None: it
        does not)."""
        p = self.problem = self._attributed(stage, state)
        limits = p.config.gates
        fits = outline_fits(p, state, stage.labels)
        return p, fits, gates.outline_misfit(fits, limits.max_coarse_bone_median_px, limits)

    def _carried(self, state: State, fits: tuple[OutlineFit, ...]) -> State | None:
        """``state`` with every view but the one whose bone fits best carried from that one
        by the encoders' motion between them, when that one fits (None otherwise).

        A view whose contour is mostly foreign edges (the femur's, a retractor's) can hold
        its pose off the bone while the other view lies on it; the encoders say where the
        first must then be, and its edges are sought from there."""
        limit = self.problem.config.gates.max_coarse_bone_median_px
        bone = {fit.view_id: fit.median_px for fit in fits if fit.label == "bone"}
        ids = [view.view_id for view in self.problem.views]
        if len(bone) < len(ids) or min(bone.values()) > limit:
            return None
        k = ids.index(min(bone, key=lambda view_id: bone[view_id]))
        keys, given = self.problem.view_keys, self.initial.T_cam_tibia
        poses = {key: given[j] @ given[k].inverse() @ state.poses[keys[k]]
                 for j, key in enumerate(keys) if j != k}
        return state.with_poses(poses)

    def _bone_edges_sought(self, stage: Stage, state: State) -> State:
        """The bone's edges sought again in each frame near the model's outline, from as
        far as the views may still be off to close by, each time with the views fitted to
        the edges found (:meth:`JointProblem.with_bone_edges_sought`)."""
        for reach_px in self.problem.config.schedule.bone_edge_reach_px:
            p = self.problem = self.problem.with_bone_edges_sought(state.poses, reach_px)
            for scale in self.problem.config.schedule.coarse_loss_scales[1:]:
                terms = p.silhouette_terms(stage.labels, 1.0, RobustLoss("cauchy", scale),
                                           thinned=stage.thinned)
                state, _ = self.lm(terms + self._odometry(stage), state, self._held(stage),
                                   self._options(stage), f"{stage.name} sought {reach_px:g} x{scale:g}")
        return state

    def _share_pin_edges(self, stage: Stage, state: State) -> None:
        """Where the pins' shadows lie on each other at ``state``, their edges shared out
        by the fit (:meth:`JointProblem.with_pin_edges_shared`)."""
        if not set(stage.labels) & set(PIN_LABELS):
            return
        self.problem, shared = self.problem.with_pin_edges_shared(state.poses)
        self.pins_shared = sorted(set(self.pins_shared) | set(shared))

    def _silhouettes(self, stage: Stage, result: StagesResult) -> StagesResult:
        """E_mp of the stage's models (only the final energy, without a budget)."""
        if stage.budget is not None:
            self._share_pin_edges(stage, result.state)
        terms = self.problem.silhouette_terms(stage.labels, 1.0, self._tight(),
                                              thinned=stage.thinned) + self._odometry(stage)
        if stage.budget is None:
            correspond(terms, result.state)
            return StagesResult(result.state, terms, result.report)
        state, report = self.lm(terms, result.state, self._held(stage), self._options(stage),
                                stage.name)
        if stage.attributed:
            self.problem = self._attributed(stage, state)
        return StagesResult(state, terms, report)

    def _attributed(self, stage: Stage, state: State) -> JointProblem:
        """The problem without the foreign edges of the stage's labels (if it drops any)."""
        if not stage.attributed or self.problem.config.sampling.foreign_edge_px is None:
            return self.problem
        return self.problem.attributed(state.poses, stage.labels)

    def _edges(self, stage: Stage, result: StagesResult) -> StagesResult:
        """The stage's edge points seated on their rays, E_rp + E_bp only."""
        p = self.problem
        points, groups = p.seated_points(result.state.poses, labels=stage.labels)
        terms = p.edge_terms(points, groups)
        state, report = self.lm(terms, State(result.state.poses, points), self._held(stage),
                                self._options(stage), stage.name)
        return StagesResult(state, terms, report)

    def _joint(self, stage: Stage, result: StagesResult) -> StagesResult:
        """The joint energy with edge points seated where their rays graze the models; after
        ``joint_seated_iterations`` seated again at the poses reached, and again while a
        stage still turns the poses by more than ``reseat_turn_deg``."""
        c = self.problem.config.schedule
        options = replace(self._options(stage), max_iterations=c.joint_seated_iterations)
        name, seatings, state = stage.name, 0, result.state
        while True:
            self._share_pin_edges(stage, state)
            p = self.problem
            points, groups = p.seated_points(state.poses, labels=stage.labels)
            terms = p.edge_terms(points, groups) + p.silhouette_terms(
                stage.labels, p.config.noise.w_mp, RobustLoss("cauchy", 3.0),
                freeze_outline=True) + self._odometry(stage)
            seated_at = state.poses
            state, report = self.lm(terms, State(state.poses, points), self._held(stage), options,
                                    name, until_settled=True)
            seatings += 1
            turned_deg = np.degrees(max(T.rotation_angle_to(state.poses[key])
                                        for key, T in seated_at.items()))
            if seatings >= c.max_seatings or (seatings > 1 and turned_deg <= c.reseat_turn_deg):
                break
            options, name = self._options(stage), f"{stage.name} reseated"
        return StagesResult(state, terms, report)
