"""What a frame hides: the bone's outline is charged, and judged, only where the frame could
show its edge (metal, collimator blades, text, the pins' shadows hide it)."""

import numpy as np
import pytest

from slamtka.sim.simulate import SimulationConfig, simulate_case
from slamtka.solver.diagnostics import outline_fits
from slamtka.solver.gates import Why
from slamtka.solver.observations import ViewObservation, VisibleRegion
from slamtka.solver.optimizer import RobustLoss, State, correspond
from slamtka.solver.problem import JointProblem, named_poses
from slamtka.solver.slam import SolverConfig, solve_joint

CELL_PX = 4


def test_a_visible_region_follows_the_distortion_and_survives_json():
    raw = np.ones((64, 80), bool)
    raw[10:20, 30:40] = False  # raw pixels u 120-159, v 40-79
    shift = np.array([8.0, 0.0])  # an ideal pixel is imaged 8 px (two cells) to the right
    region = VisibleRegion.from_raw(raw, CELL_PX, (320, 256), lambda uv: uv + shift)
    assert region.cells.shape == (64, 80)
    assert not region.cells[10:20, 28:38].any() and region.cells[10:20, 38:40].all()
    assert region.contains(np.array([[115.0, 60.0], [155.0, 60.0], [-1.0, 5.0], [321.0, 5.0]])).tolist() == \
        [False, True, False, False]
    again = VisibleRegion.from_json(region.to_json())
    assert again.cell_px == CELL_PX and np.array_equal(again.cells, region.cells)
    with pytest.raises(ValueError, match="needs"):
        VisibleRegion.from_json({**region.to_json(), "shape": [640, 800]})


def _hidden_band(view: ViewObservation, share: float) -> ViewObservation:
    """``view`` as if metal lay across the first ``share`` of its bone contour (by image row):
    the contour is gone there and the frame says so."""
    bone = view.contours["bone"]
    top = float(np.quantile(bone[:, 1], share))
    h, w = -(-view.camera.height // CELL_PX), -(-view.camera.width // CELL_PX)
    cells = np.ones((h, w), bool)
    cells[: int(np.ceil(top / CELL_PX))] = False
    region = VisibleRegion(cells, CELL_PX)
    return ViewObservation(view.view_id, view.camera, {**view.contours, "bone": bone[region.contains(bone)]},
                           view.notes, region)


def _outline_distances(plan, views, state) -> np.ndarray:
    terms = JointProblem(plan, views, SolverConfig()).silhouette_terms(("bone",), 1.0, RobustLoss("l2"))
    correspond(terms, state)
    return terms[0].distances_px(state)[0]


def test_a_hidden_part_of_the_outline_is_not_charged_and_does_not_pull(phantom_plan):
    """With 60% of view 1's bone contour under metal, the outline there at the true poses is
    tens of pixels from any contour. Not told what the frame hides, the solve reads that as a
    bone off its contour and refuses; told, the silhouette term charges none of it, the gate
    reads the rest, and the solve measures as without metal (so on seeds 0-5, against 1 of
    6 measured unmarked)."""
    case = simulate_case(phantom_plan, SimulationConfig(seed=0))
    hidden = [_hidden_band(case.views[0], 0.6)] + case.views[1:]
    unmarked = [ViewObservation(hidden[0].view_id, hidden[0].camera, hidden[0].contours)] + hidden[1:]
    truth = State(named_poses(case.truth_T_cam_tibia, case.truth_T_tibia_pin), np.zeros((0, 3)))
    assert np.max(_outline_distances(phantom_plan, unmarked, truth)) > 20.0
    assert np.max(_outline_distances(phantom_plan, hidden, truth)) < 5.0
    fit = outline_fits(JointProblem(phantom_plan, hidden, SolverConfig()), truth, ("bone",))[0]
    assert 0.4 < fit.visible_share < 0.8 and fit.median_px < 1.5
    assert solve_joint(phantom_plan, unmarked, case.initial,
                       SolverConfig(global_searches=())).status == "not_measured"
    outcome = solve_joint(phantom_plan, hidden, case.initial)
    assert outcome.status == "measured", outcome.reason
    ctr, str_ = np.degrees([outcome.plane.ctr, outcome.plane.str_])
    assert abs(ctr - case.truth_ctr_deg) < 0.3 and abs(str_ - case.truth_str_deg) < 0.3


def test_a_view_whose_outline_is_mostly_hidden_is_refused_naming_it(phantom_plan):
    case = simulate_case(phantom_plan, SimulationConfig(seed=3))
    views = case.views[:1] + [_hidden_band(case.views[1], 0.8)]
    outcome = solve_joint(phantom_plan, views, case.initial)
    assert outcome.status == "not_measured"
    assert outcome.why is Why.BONE_OUTLINE_INSUFFICIENT
    assert f"view {views[1].view_id}: too little of the tibia outline is visible" in outcome.reason
