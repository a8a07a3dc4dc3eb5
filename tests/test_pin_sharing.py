"""Pins seen on each other in a radiograph: their edges shared out by the fit
(JointProblem.with_pin_edges_shared), and refused where no view shows how far apart they are."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from slamtka.bench.realism import SHARED_DATA, realism_case
from slamtka.sim.simulate import SimulationConfig, simulate_case
from slamtka.solver.observations import PIN_LABELS
from slamtka.solver.problem import JointProblem, named_poses
from slamtka.solver.solver_config import SamplingConfig, SolverConfig

MESHES = SHARED_DATA / "knee-nuisance"
SHARING = SolverConfig(sampling=SamplingConfig(share_pin_edges=True))


def _outline_distances(problem: JointProblem, k: int, poses, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) distances of ``pixels`` to pin 1's and pin 2's outlines in view ``k``."""
    columns = []
    for label in PIN_LABELS:
        outline = problem._outline_px(k, label, poses)
        columns.append(np.min(np.linalg.norm(pixels[:, None] - outline[None], axis=2), axis=1))
    return np.column_stack(columns)


@pytest.fixture(scope="module")
def in_line_case(phantom_plan):
    """Seed 3: in both views the pins lie along one image line, partly on each other."""
    case = simulate_case(phantom_plan, SimulationConfig(seed=3, noise_px=0.0))
    return case, named_poses(case.truth_T_cam_tibia, case.truth_T_tibia_pin)


def test_the_pin_edges_of_an_opaque_view_go_to_the_nearer_pin(phantom_plan, in_line_case):
    case, poses = in_line_case
    rng = np.random.default_rng(0)
    pooled = np.vstack([case.views[0].contours[label] for label in PIN_LABELS])
    named_at_random = rng.random(len(pooled)) < 0.5
    view = replace(case.views[0].with_contours(pin1=pooled[named_at_random], pin2=pooled[~named_at_random]),
                   pins_opaque=True)
    problem = JointProblem(phantom_plan, [view, case.views[1]], SHARING)
    assert problem.pins_touch(poses)
    shared_problem, shared = problem.with_pin_edges_shared(poses)
    assert shared == [view.view_id]
    ambiguity = SHARING.sampling.pin_edge_ambiguity_px
    got = shared_problem.views[0]
    for own, label in enumerate(PIN_LABELS):
        d = _outline_distances(problem, 0, poses, got.contours[label])
        assert np.all(d[:, own] + ambiguity <= d[:, 1 - own] + 1e-6)
    kept = sum(len(got.contours[label]) for label in PIN_LABELS)
    assert 0.5 * len(pooled) < kept <= len(pooled)
    # Each pin's outline counts only outside the other's shadow.
    for label, other in zip(PIN_LABELS, reversed(PIN_LABELS)):
        assert got.pins_visible is not None
        inside_other = problem._outline_px(0, other, poses).mean(axis=0, keepdims=True)
        assert not got.pins_visible[label].contains(inside_other)[0]
    # Shared once, the view is shared out again from the same pooled edges.
    again, shared_again = shared_problem.with_pin_edges_shared(poses)
    assert shared_again == [view.view_id]
    for label in PIN_LABELS:
        np.testing.assert_array_equal(again.views[0].contours[label], got.contours[label])


def test_contours_drawn_pin_by_pin_keep_their_names(phantom_plan, in_line_case):
    case, poses = in_line_case
    problem = JointProblem(phantom_plan, case.views, SHARING)
    assert not problem.pins_touch(poses)
    assert problem.with_pin_edges_shared(poses) == (problem, [])
    # Nor is an opaque view shared out unless a solve refused over the pins asks for it.
    opaque = [replace(view, pins_opaque=True) for view in case.views]
    unasked = JointProblem(phantom_plan, opaque, SolverConfig())
    assert unasked.with_pin_edges_shared(poses) == (unasked, [])


def test_a_bar_the_extraction_gave_both_pins_is_shared_out_from_the_first_solve(phantom_plan, in_line_case):
    """Where the extraction saw the pins one behind the other, it gives both pins the bar's
    edges and pools them (``pin_edges``): the fit shares them out from the first solve on,
    unasked, rather than fit each pin to the whole bar (which slid and turned them)."""
    case, poses = in_line_case
    pooled = np.vstack([case.views[0].contours[label] for label in PIN_LABELS])
    behind = replace(case.views[0].with_contours(pin1=pooled, pin2=pooled), pins_opaque=True,
                     pin_edges=pooled)
    problem = JointProblem(phantom_plan, [behind, case.views[1]], SolverConfig())
    shared_problem, shared = problem.with_pin_edges_shared(poses)
    assert shared == [behind.view_id]
    got = shared_problem.views[0]
    assert sum(len(got.contours[label]) for label in PIN_LABELS) <= len(pooled)
    assert len(got.contours["pin1"]) < len(pooled) and len(got.contours["pin2"]) < len(pooled)


@pytest.mark.system
@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_pins_that_touch_end_to_end_in_one_view_are_measured():
    """Idealised seed 12, view 2: the pins lie nearly in line, touching end to end, and
    extraction split their one bar 150 px from where one pin ends (refused: "the pin1
    outline in view view2 leaves its contour"). Solved again with the bar's edges shared
    out by the fit, it measures."""
    row = realism_case(("phantom", "idealised", 12, (1,), str(SHARED_DATA)))
    assert row["levels"][1]["status"] == "success", row["levels"][1]


@pytest.mark.system
@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_pins_one_behind_the_other_in_one_view_are_measured():
    """Surgeon's views seed 1: view 1 (-50 deg) sees the pins one behind the other (94% of
    a pin's shadow on the other's), and extraction called the one bar pin 1 and its tip
    pin 2; refused before, naming the view. The other view tells the pins apart, and the
    bar's edges shared out by the fit measure it."""
    row = realism_case(("phantom", "views", 1, (1,), str(SHARED_DATA)))
    assert row["levels"][1]["status"] == "success", row["levels"][1]


@pytest.mark.system
@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_pins_in_line_and_on_each_other_in_every_view_are_not_shared_out():
    """Idealised seed 16: in both views the pins lie in line, one partly on the other, so
    each pin's inner end hides in the other's shadow. Shared out by the fit, the case was
    measured 4.2 deg off in CTR with a sigma of 1.1 deg; asked for from the start, sharing
    must refuse, saying why. Unshared, the pins' names are settled by the bone and the case
    is measured."""
    row = realism_case(("phantom", "idealised", 16, (1,), str(SHARED_DATA)))["levels"][1]
    assert row["status"] == "success", row
    assert max(row["ctr_abs_deg"], row["str_abs_deg"]) < 0.5, row
    shared = realism_case(("phantom", "idealised", 16, (1,), str(SHARED_DATA)), SHARING)["levels"][1]
    assert shared["status"] == "refused", shared
    assert "the two pins lie in line, one on the other, in every view" in shared["reason"]


@pytest.mark.system
@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_a_case_refused_for_its_pins_names_is_not_tried_again_sharing_their_edges():
    """The real tibia's seed 3 behind collimator shutters: the other naming fits as well
    (final cost 558 against 528) but is refused, and the bone does not settle the names, so
    the case is refused. Sharing the touching pins' edges cannot say which pin is which
    across views (a headed-pins case so retried was once measured 14 deg off); the refusal
    stands. (The idealised frames of that seed, refused so before, are measured since their
    unstepped bar is shared from the start; surgeon's views seed 12 is named by the
    encoders' motion.)"""
    result = realism_case(("real", "shutters", 3, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "refused", result
    assert "cannot be told apart" in result["reason"]


@pytest.mark.system
@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_headed_pins_whose_namings_both_fit_are_named_by_the_bone():
    """Headed pins seed 26: both namings fit, giving planes 14.9 deg apart; at level 3 the
    wrong one fits better by a final cost of 112, most of it in the silhouette term of
    headless pin models over headed pins, and counted in that term's dispersion no better.
    The fit cannot decide (once refused at both levels); the naming that keeps both pins in
    the bone is the right one, and the case is measured."""
    levels = realism_case(("phantom", "headed_pins", 26, (1, 3), str(SHARED_DATA)))["levels"]
    for level in (1, 3):
        assert levels[level]["status"] == "success", (level, levels[level])
        assert max(levels[level]["ctr_abs_deg"], levels[level]["str_abs_deg"]) < 0.5, (level, levels[level])
