"""What a frame hides: the bone's outline is charged, and judged, only where the frame could
show its edge (metal, collimator blades, text, the pins' shadows hide it)."""

from dataclasses import replace

import numpy as np
import pytest

from slamtka.sim.simulate import SimulationConfig, default_camera, simulate_case
from slamtka.sim.xray import XRayParams, render_radiograph
from slamtka.solver.diagnostics import outline_fits
from slamtka.solver.gates import Why
from slamtka.solver.imaging.contours import extract_contours
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


def _pin_out_of_field(view: ViewObservation, label: str, field_ends_at_u: float) -> ViewObservation:
    """``view`` as if the exposed field ended at column ``field_ends_at_u``, across ``label``'s
    shadow: its contour is gone beyond, and the frame says where pins can be seen."""
    h, w = -(-view.camera.height // CELL_PX), -(-view.camera.width // CELL_PX)
    cells = np.ones((h, w), bool)
    cells[:, int(field_ends_at_u // CELL_PX):] = False
    field = VisibleRegion(cells, CELL_PX)
    pin = view.contours[label]
    return replace(view.with_contours(**{label: pin[field.contains(pin)]}), pin_field=field)


def test_a_pin_running_out_of_the_field_is_charged_only_inside_it(phantom_plan):
    """A pin's shadow running out of the exposed field (a long pin in an oblique view, the
    field's edge or a collimator blade) has no contour beyond it. Told where the field ends,
    the pin's outline there is not charged, and the gate reads what is left: at the true
    poses, with half of pin 1's shadow out of view 1's field, the outline's tenth farthest
    from the contour lies tens of pixels off unmarked (the gate's limit is 60 px) and on it
    marked."""
    case = simulate_case(phantom_plan, SimulationConfig(seed=0))
    pin = case.views[0].contours["pin1"]
    cut = [_pin_out_of_field(case.views[0], "pin1", float(np.median(pin[:, 0])))] + case.views[1:]
    unmarked = [replace(cut[0], pin_field=None)] + cut[1:]
    truth = State(named_poses(case.truth_T_cam_tibia, case.truth_T_tibia_pin), np.zeros((0, 3)))

    def pin1_p90(views: list[ViewObservation]) -> float:
        fits = outline_fits(JointProblem(phantom_plan, views, SolverConfig()), truth, ("pin1",))
        return next(fit.p90_px for fit in fits if fit.view_id == views[0].view_id)

    assert pin1_p90(unmarked) > 20.0
    assert pin1_p90(cut) < 2.0
    outcome = solve_joint(phantom_plan, cut, case.initial)
    assert outcome.status == "measured", outcome.reason
    ctr, str_ = np.degrees([outcome.plane.ctr, outcome.plane.str_])
    assert abs(ctr - case.truth_ctr_deg) < 0.3 and abs(str_ - case.truth_str_deg) < 0.3


def test_the_extraction_says_pins_are_seen_only_inside_the_field(phantom_plan):
    """An image intensifier's round field: outside the circle no pin's edge can be seen, and
    the observation carries that to the solver over undistorted pixels."""
    case = simulate_case(phantom_plan, SimulationConfig(seed=0))
    camera = default_camera()
    r = render_radiograph(phantom_plan, case.truth_T_cam_tibia[0], case.truth_T_tibia_pin, camera, XRayParams(),
                          np.random.default_rng(0))
    found = extract_contours(r.image)
    seen = VisibleRegion(found.pins_visible, found.visible_cell_px)
    centre, radius = np.array(found.diagnostics["fov_centre_px"]), found.diagnostics["fov_radius_px"]
    corners = np.array([[4.0, 4.0], [camera.width - 4.0, camera.height - 4.0]])
    assert not seen.contains(corners).any() and seen.contains(centre[None]).all()
    assert seen.contains(centre[None] + [0.8 * radius, 0.0]).all()
    observed = found.observation("v", camera, r.distortion.undistort, r.distortion.distort)
    assert observed.pin_field is not None and not observed.pin_field.contains(corners).any()
