"""Operating-room frames: extraction never fails but by name, the simulator's nuisances,
and a CI-sized realism study (no wrong angle; refusals say why)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from slamtka.bench.realism import SHARED_DATA, _scores, realism_case
from slamtka.service.cli import main
from slamtka.sim.operating_room import (
    NUISANCES,
    OperatingRoom,
    render_room,
    room_bodies,
    room_scene,
    view_angles,
)
from slamtka.sim.simulate import SimulationConfig, default_camera, simulate_case
from slamtka.sim.xray import XRayParams
from slamtka.solver.imaging.contours import UNFORESEEN_PREFIX, ContourError, extract_contours
from slamtka.solver.imaging.field import field_of_view, remove_overlays
from slamtka.solver.imaging.response import frame_attenuation, linearised_attenuation
from slamtka.solver.solver_config import ScheduleConfig, SolverConfig

from frame_variants import TRANSFORMS, made_up_frames  # isort: skip

MESHES = SHARED_DATA / "knee-nuisance"


@pytest.fixture(scope="module")
def clean_frames(radiographs):
    return [r.image for r in radiographs[1]]


def _room_case(plan, room: OperatingRoom, seed: int):
    draw = room.draw(seed)
    return draw, simulate_case(plan, SimulationConfig(seed=seed, view_angles_deg=view_angles(draw, (-30.0, 30.0))))


def _room_frames(plan, scene, room: OperatingRoom, seed: int):
    draw, case = _room_case(plan, room, seed)
    rng = np.random.default_rng(seed)
    bodies = room_bodies(plan, draw)
    scene = room_scene(scene, draw)
    return draw, [render_room(plan, T, case.truth_T_tibia_pin, default_camera(), XRayParams(), draw, rng,
                              scene, bodies) for T in case.truth_T_cam_tibia]


def test_extraction_raises_only_its_own_named_error_whatever_the_frame(clean_frames):
    """Processed, inverted, cropped, flat-panel-like, 8-16 bit, signed, float, tiny, uniform,
    saturated, noise: each frame is either extracted or refused with a ContourError that
    names the cause (never the catch-all of an unforeseen failure)."""
    rng = np.random.default_rng(0)
    frames = [(f"{name} of view 0", transform(clean_frames[0], rng)) for name, transform in TRANSFORMS.items()]
    frames += list(made_up_frames(rng))
    refused = {}
    for name, frame in frames:
        try:
            extract_contours(frame)
        except ContourError as exc:
            assert not str(exc).startswith(UNFORESEEN_PREFIX), f"{name}: {exc}"
            refused[name] = str(exc)
    assert "uniform" in refused["uniform"]
    assert "non-finite" in refused["nan"]
    assert "64 x 64" in refused["colour"]
    # Every transform of a real frame that keeps the knee in view is extracted.
    for name in ("as rendered", "inverted", "8-bit window", "16-bit", "log response", "log inverted",
                 "unsharp masked", "gamma", "flat panel", "flat panel inverted", "shifted signed", "float",
                 "half float"):
        assert f"{name} of view 0" not in refused, refused.get(f"{name} of view 0")


def test_a_frame_of_twice_the_pixels_is_extracted_as_the_frame_itself(clean_frames):
    """A flat panel's 2048 px frame is reduced to the extraction's working size: a frame
    whose pixels are each repeated 2 x 2 gives the contours of the frame itself, on its own
    pixels (each at the centre of its block), and a bone region of cells twice as large."""
    frame = clean_frames[0]
    large = np.repeat(np.repeat(frame, 2, axis=0), 2, axis=1)
    found, found_large = extract_contours(frame), extract_contours(large)
    assert found_large.diagnostics["working_scale"] == 2 and "working_scale" not in found.diagnostics
    for label, points in found.as_dict().items():
        assert len(points) > 0
        assert np.allclose(found_large.as_dict()[label], 2.0 * points + 0.5, rtol=0.0, atol=1e-9), label
    assert np.array_equal(found_large.bone_visible, found.bone_visible)
    assert found_large.visible_cell_px == 2 * found.visible_cell_px
    assert found_large.bone_edge_search is not None and found_large.bone_edge_search.scale == 2


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize(("pixels", "seed"), [(1536, 0), (2048, 1)])
def test_frames_of_a_larger_detector_are_measured(monkeypatch, pixels, seed):
    """The same C-arm with a detector of 1536 or 2048 px a side: extracted directly, these
    frames measured seed 0 0.28 deg off in CTR and 0.8 in STR at 1536 px and refused seed 1
    at 2048 px (pin 1's outline 3.8 px off its contour); reduced, they measure as at 1024 px."""
    import slamtka.sim.simulate as simulated

    monkeypatch.setattr(simulated, "DETECTOR_PIXELS", pixels)
    result = realism_case(("phantom", "idealised", seed, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "success", result
    assert max(result["ctr_abs_deg"], result["str_abs_deg"]) < 0.2


def test_polarity_comes_from_the_content_of_flat_panel_and_processed_frames(clean_frames):
    T = TRANSFORMS

    rng = np.random.default_rng(1)
    for name, expected in (("flat panel", 1), ("flat panel inverted", -1), ("log inverted", -1),
                           ("unsharp masked", 1)):
        _, radius, _, sign, _ = field_of_view(T[name](clean_frames[0], rng), "auto")
        assert sign == expected, name
        assert (radius is None) == name.startswith("flat panel"), name


def test_each_nuisance_is_a_seedable_option_and_femur_flexion_swings_backwards(phantom_plan):
    assert set(OperatingRoom.everything().names) == set(NUISANCES) - {"unsharpness"}
    with pytest.raises(ValueError, match="unknown nuisance"):
        OperatingRoom.only("fog")
    with pytest.raises(ValueError, match=r"\['fog'\]"):
        OperatingRoom.of(["femur", "fog"])
    assert OperatingRoom.of(["retractors", "femur"]).names == ["femur", "retractors"]
    room = OperatingRoom.only("femur", MESHES)
    a, b = room.draw(5), room.draw(5)
    assert a.flexion_deg == b.flexion_deg and 70.0 <= a.flexion_deg <= 110.0
    (name, femur), = room_bodies(phantom_plan, a)
    assert name == "femur"
    # Flexed, the femur's shaft runs from the knee towards the back (-y), not the front.
    v = femur.vertices
    far = v[np.argsort(np.linalg.norm(v, axis=1))[-50:]].mean(axis=0)
    assert far[1] < -80.0
    assert far[2] < 120.0


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_operating_room_frames_carry_their_nuisances_and_hidden_truth(phantom_plan, scene):
    draw, frames = _room_frames(phantom_plan, scene, OperatingRoom.everything(MESHES), 3)
    frame = frames[0]
    assert frame.radiograph.camera.fov_radius_px is None  # a flat panel
    assert frame.radiograph.image.max() <= (1 << draw.processing["bits"]) - 1
    assert {"femur", "patella", "retractor"} <= set(frame.foreign)
    assert 0 < frame.hidden["bone"].sum() < len(frame.hidden["bone"])
    cleaned, strokes = remove_overlays(frame.radiograph.image)
    assert strokes.sum() > 500  # the burned-in text


@pytest.mark.parametrize("scene_name, seeds", [("idealised", (0,)), ("flat_panel", (0,)),
                                               ("retractors", (1,)), ("operating-room", (0, 1))])
def test_ci_realism_cases_are_measured_right_or_refused_with_a_reason(phantom_plan, scene_name, seeds):
    """A few cases per scene: never a wrong angle, and every refusal names its cause."""
    for seed in seeds:
        row = realism_case(("phantom", scene_name, seed, (1,), str(SHARED_DATA)))
        result = row["levels"][1]
        assert result["status"] in ("success", "refused"), result
        if result["status"] == "refused":
            assert len(result["reason"]) > 20 and "Error" not in result["reason"]
        if scene_name == "idealised":
            assert result["status"] == "success"


@pytest.mark.parametrize("scene_name, seed, level", [("idealised", 28, 1), ("idealised", 0, 3),
                                                     ("views", 22, 3)])
def test_names_from_the_bone_and_pins_seen_end_on_at_level_3_are_measured(scene_name, seed, level):
    """Idealised seed 28 at level 1: the fit and the pins' sightings disagree about the pins'
    names; the naming with both pins in the bone is taken (it was refused). Seed 0 at level
    3: the initial pose foresees 520 px shadows for pins that cast 156 px; two parallel bars
    of a pin's width are taken (no pin was found). Surgeon's views seed 22 at level 3: a
    view shows the pins 88% on each other, so the bone, which put the right naming's pin
    7 mm out, has no say, and the fit's clear choice stands (it was refused)."""
    row = realism_case(("phantom", scene_name, seed, (level,), str(SHARED_DATA)))
    assert row["levels"][level]["status"] == "success", row["levels"][level]


@pytest.mark.parametrize("scene_name, seed, level", [("processing", 18, 1), ("marker", 15, 1),
                                                     ("idealised", 2, 3), ("views", 12, 1)])
def test_pins_clipped_touched_or_misnamed_are_measured(scene_name, seed, level):
    """Processing seed 18: an inverted frame whose window clipped the pins white in patches
    between the noise; the patches were taken for burned-in text and the pins removed with
    them. Marker seed 15: a lead marker's stroke touching pin 1 made its bar 62 px wide, and
    its edges were left off it. Idealised seed 2 at level 3: the first naming's outlines do
    not fit (2.7 px), the other's do and agree better with the encoders. Surgeon's views
    seed 12: the fit and the pins' sightings disagree about the names, and the encoders'
    motion sides clearly with the fit (2.3 against 5.0 sigma RMS). All were refused."""
    row = realism_case(("phantom", scene_name, seed, (level,), str(SHARED_DATA)))
    assert row["levels"][level]["status"] == "success", row["levels"][level]


def test_a_naming_that_fits_better_by_straining_the_encoders_is_not_taken():
    """Scatter seed 16: the first naming's pins are 3.4 deg from parallel; the other fits
    better and the bone prefers it, but it moves the views against the encoders (5.1 to 7.3
    sigma) and was measured 1.07 deg off in STR. Refused."""
    row = realism_case(("phantom", "scatter", 16, (1,), str(SHARED_DATA)))
    assert row["levels"][1]["status"] == "refused", row["levels"][1]


@pytest.mark.parametrize("seed", [14, 23])
def test_a_frame_misread_inverted_is_read_as_its_partner_clearly_shows(seed):
    """Shutters seeds 14 and 23: view 1's periphery said little about its polarity and a
    collimator blade's bright edge passed for steel, so it was read inverted and the bone
    stage went astray (refused); view 2's periphery clearly says "dark", and one C-arm
    stores both frames alike."""
    row = realism_case(("phantom", "shutters", seed, (1,), str(SHARED_DATA)))
    assert row["levels"][1]["status"] == "success", row["levels"][1]


@pytest.mark.parametrize("scene_name, seed", [("scatter", 29), ("dose", 8)])
def test_a_fit_refused_on_the_first_contour_is_measured_on_edges_sought_near_it(scene_name, seed):
    """Scatter seed 29: the first contour of view 2 holds the fibula's and the plateau's
    rim's edges inside the outline and misses part of its side; fitted to it the views end
    9 sigma from the encoders. Dose seed 8: its bone 2.6 px off its contour (> 2.5). Both
    were refused; on the edges sought again near the outline each solve reached, both
    measure."""
    row = realism_case(("phantom", scene_name, seed, (1,), str(SHARED_DATA)))
    assert row["levels"][1]["status"] == "success", row["levels"][1]


def test_a_solve_the_encoders_contradict_is_restarted_from_a_view_carried_by_them():
    """Retractors seed 3: the solve ended in a local minimum the encoders' motion
    contradicts (E_odo 7.9 sigma RMS: view 1 2.8 deg off, view 2 0.65), and the global
    searches did not leave it. Restarted from view 2 with view 1 carried from it by the
    encoders' motion, it measures."""
    row = realism_case(("phantom", "retractors", 3, (1,), str(SHARED_DATA)))
    assert row["levels"][1]["status"] == "success", row["levels"][1]


@pytest.mark.skipif(not (SHARED_DATA / "knee-smith2019" / "tibia-right.stl").is_file(),
                    reason="shared meshes absent")
def test_pins_in_line_between_blades_are_not_taken_for_pins_one_behind_the_other():
    """The real tibia's operating-room seed 26 at level 3: between two retractor blades,
    view 2 shows a piece of two pins in line, one overlapping the other's end, wider only
    where they overlap. Given to both pins as one bar, the case was measured 5.0 deg off in
    CTR; not taken for them, it is refused."""
    row = realism_case(("real", "operating-room", 26, (3,), str(SHARED_DATA)))
    assert row["levels"][3]["status"] == "refused", row["levels"][3]


@pytest.mark.skipif(not (SHARED_DATA / "knee-smith2019" / "tibia-right.stl").is_file(),
                    reason="shared meshes absent")
@pytest.mark.parametrize("model, scene_name, seed, level", [("phantom", "headed_pins", 3, 1),
                                                            ("real", "idealised", 11, 3)])
def test_pins_in_one_shadow_read_from_heads_and_steps_are_measured(model, scene_name, seed, level):
    """Headed pins seed 3, view 1: pins in line with no step, split in the middle, each cut
    short (the head on the other's shaft now says where that pin begins). The real tibia's
    idealised seed 11 at level 3, view 1: pins in line whose sides step, 139 and 153 px long
    where the initial pose foresaw 381, were not taken (a stepped split is now taken
    whatever the length). Both were refused."""
    row = realism_case((model, scene_name, seed, (level,), str(SHARED_DATA)))
    assert row["levels"][level]["status"] == "success", row["levels"][level]


def test_bench_realism_writes_results_and_montage(tmp_path):
    out = tmp_path / "realism"
    assert main(["bench", "realism", "--cases", "1", "--levels", "1", "--models", "phantom",
                 "--scenes", "idealised,shutters+text", "--out", str(out)]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert [e["scene"] for e in doc["summary"]] == ["idealised", "shutters+text"]
    assert "L1 success" in (out / "results.md").read_text()
    assert (out / "montage.png").stat().st_size > 10_000


def test_bench_realism_refuses_an_unknown_nuisance_in_a_combined_scene(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "realism", "--scenes", "femur+drapes", "--out", "/nonexistent"])
    assert exit_.value.code == 2
    assert "unknown nuisance(s) ['drapes']" in capsys.readouterr().err


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_simulate_writes_operating_room_frames_with_truth_and_the_patient_given(tmp_path):
    import pydicom

    out = tmp_path / "case"
    assert main(["simulate", "--out", str(out), "--images", "--scene", "operating-room", "--seed", "4",
                 "--patient-id", "OR-17", "--patient-name", "ROE^RICHARD"]) == 0
    truth = json.loads((out / "truth_silhouettes.json").read_text())
    assert set(truth["nuisances"]) == set(OperatingRoom.everything().names)
    assert all("hidden" in view for view in truth["views"])
    ds = pydicom.dcmread(out / "frames" / "view1.dcm")
    assert ds.PatientID == "OR-17" and str(ds.PatientName) == "ROE^RICHARD"
    assert json.loads((out / "plan" / "plan.json").read_text())["patient_id"] == "OR-17"
    calibration = json.loads((out / "calibration.json").read_text())
    assert "flat-panel" in json.dumps(calibration)
    assert main(["simulate", "--out", str(tmp_path / "x"), "--femur"]) == 2  # frames are needed



def test_a_log_stored_frame_is_read_as_attenuation_from_its_own_noise(clean_frames):
    """The same frame stored raw and through a windowed log response: -log of the log
    frame's grey levels is not attenuation (the bone's contrast shrinks several times); the
    quanta's noise tells how to undo the response, and the attenuation comes back with its
    contrast within 15%. The raw frame is left to the exact -log of its signal."""
    raw = clean_frames[0]
    centre, radius, outside, sign, _ = field_of_view(raw, "auto")
    v, u = np.mgrid[0:raw.shape[0], 0:raw.shape[1]]
    lit = np.hypot(u - centre[0], v - centre[1]) < radius - 10
    assert linearised_attenuation(raw, lit, sign) is None
    truth = -np.log(np.maximum(raw.astype(float) - outside, 1.0))
    stored = TRANSFORMS["log response"](raw, np.random.default_rng(0))
    A = linearised_attenuation(stored, lit, 1)
    assert A is not None
    # Over the leg (not the saturated steel, not air): attenuation against the truth.
    leg = lit & (truth > np.percentile(truth[lit], 30)) & (truth < np.percentile(truth[lit], 97))
    slope = np.polyfit(truth[leg], A[leg], 1)[0]
    assert slope == pytest.approx(1.0, abs=0.15)
    naive = -np.log(np.maximum(stored.astype(float), 1.0))
    assert abs(np.polyfit(truth[leg], naive[leg], 1)[0]) < 0.5


def test_a_log_stored_frame_whose_noise_8_bits_quantise_away_is_read_from_its_spread(clean_frames):
    """Stored through a log response in 8 bits, a frame's noise is quantised away and cannot
    show the response: read as linear, its attenuation spans less than half the raw
    frame's (in processing seed 23 a sixth: half the leg passed for air). It is read as
    log-stored instead, with the
    bone's contrast within a factor 1.6 of the truth; the raw frame stays linear."""
    raw = clean_frames[0]
    centre, radius, outside, sign, _ = field_of_view(raw, "auto")
    v, u = np.mgrid[0:raw.shape[0], 0:raw.shape[1]]
    lit = np.hypot(u - centre[0], v - centre[1]) < radius - 10
    truth, response = frame_attenuation(raw, lit, outside, sign)
    truth = truth.astype(float)
    assert response == "linear"
    stored = np.round(255 * (np.log(np.maximum(raw.astype(float) - outside, 1.0)) / np.log(raw.max() - outside)))
    stored = np.clip(stored, 0, 255).astype(np.uint8)
    A, response = frame_attenuation(stored, lit, 0.0, sign)
    A = A.astype(float)
    assert response == "log-stored, read from its spread"
    leg = lit & (truth > np.percentile(truth[lit], 30)) & (truth < np.percentile(truth[lit], 97))
    naive = -np.log(np.maximum(stored.astype(float), 1.0))
    assert np.polyfit(truth[leg], naive[leg], 1)[0] < 0.5
    assert 1 / 1.6 < np.polyfit(truth[leg], A[leg], 1)[0] < 1.6


def test_a_raw_frame_whose_noise_a_blurring_detector_smooths_below_a_grey_level_stays_linear(clean_frames):
    """A worn intensifier blurs 1.5-2 px: a raw frame's quantum noise is then smoothed to
    under one grey level, where its SD (a median of whole quarter levels) moves in steps
    and its variance is no longer linear in the level (the unsharpness scene's frames were
    read as processed, a plateau's band at three times its attenuation). Noise under one
    stored level whose variance still rises with the level, as the quanta's does, is a raw
    frame's: it is read as linear, its attenuation as the sharp frame's."""
    raw = clean_frames[0]
    centre, radius, outside, sign, _ = field_of_view(raw, "auto")
    v, u = np.mgrid[0:raw.shape[0], 0:raw.shape[1]]
    lit = np.hypot(u - centre[0], v - centre[1]) < radius - 10
    truth, _ = frame_attenuation(raw, lit, outside, sign)
    blurred = np.round(cv2.GaussianBlur(raw.astype(np.float32), (0, 0), 1.8)).astype(raw.dtype)
    A, response = frame_attenuation(blurred, lit, outside, sign)
    assert response == "linear"
    leg = lit & (truth > np.percentile(truth[lit], 30)) & (truth < np.percentile(truth[lit], 97))
    assert np.polyfit(truth[leg].astype(float), A[leg].astype(float), 1)[0] == pytest.approx(1.0, abs=0.05)


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize(("seed", "least_coverage"), [(2, 0.6), (3, 0.6), (23, 0.55)])
def test_a_log_processed_frame_yields_most_of_the_visible_outline(phantom_plan, scene, seed, least_coverage):
    """Seed 2 of the processing scene (log response, unsharp masking, gamma 1.17): read as
    -log of its grey levels the bone mask leaked (coverage 0% and 27%); linearised from
    its noise, with the rim's sharpening halo left out, most of the outline is found.
    Seed 3 (stored inverted, gamma 1.5, unsharp masking at 25 px): half the field's
    tissue changed faster than the soft-tissue barrier, the mask leaked into it (13% and
    5%); the barrier now rises with the field's own median gradient. Seed 23 (log
    response, gamma 1.5, 8 bits): its noise could not show the response, half the leg
    passed for air (coverage 10% and 29%); it is read from its spread."""
    draw, frames = _room_frames(phantom_plan, scene, OperatingRoom.only("processing", MESHES), seed)
    assert draw.processing["log"]
    for frame in frames:
        found = extract_contours(frame.radiograph.image)
        assert found.diagnostics["response"] != "linear"
        assert _scores(frame, found)["coverage"] >= least_coverage


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_the_frame_says_where_a_bone_edge_could_not_be_seen(phantom_plan, scene):
    """Collimator blades hide 10% and 8% of the true outline in seed 0's two views: the
    visible region extraction hands the solver leaves out all but a few percent of it and
    keeps nearly all the rest."""
    _, frames = _room_frames(phantom_plan, scene, OperatingRoom.only("shutters", MESHES), 0)
    for frame in frames:
        found = extract_contours(frame.radiograph.image)
        d = frame.radiograph.distortion
        region = found.observation("v", frame.radiograph.camera, d.undistort, d.distort).bone_visible
        truth, hidden = d.undistort(frame.radiograph.silhouettes["bone"]), frame.hidden["bone"]
        shown = ~hidden & frame.radiograph.camera.in_field(truth, 8.0)
        assert hidden.mean() > 0.05
        assert np.mean(region.contains(truth[hidden])) < 0.1
        assert np.mean(region.contains(truth[shown])) > 0.95


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_pins_seen_one_behind_the_other_are_refused_naming_the_view():
    """Seed 14 of the surgeon's views: view 1 sees the pins one behind the other (75% of a
    pin's shadow on the other's). Their outlines do not fit, nor do they once the bar's
    edges are shared out by the fit, and the refusal says why, naming the view. (Seed 1,
    refused so before, is now measured that way: tests/test_pin_sharing.py.)"""
    row = realism_case(("phantom", "views", 14, (1,), str(SHARED_DATA)))
    result = row["levels"][1]
    assert result["status"] == "refused"
    assert result["reason"].startswith("view view1: the two pins lie one behind the other")
    # Its pins turn 4.4 deg apart within their plane, 10.6 times what the views resolve of
    # that turn: a wrong pose (the plane 4.9 deg off), refused as not parallel.
    assert "4.4 deg from parallel" in result["reason"]


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize("scene_name", ["femur", "text"])
def test_pins_whose_turn_within_their_plane_the_views_cannot_resolve_are_measured(scene_name):
    """Seed 16: both views see the pins' plane nearly edge-on, the pins in line. The plane
    is sure, but the pins' turn within it rests on their ends alone: they come out 3.1-3.2
    deg apart within it, 2.6-3.5 times its standard deviation, and the angles right within
    0.1 deg. Refused before as not parallel or, the other naming, as degenerate."""
    result = realism_case(("phantom", scene_name, 16, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "success", result


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize("seed", [5, 15])
def test_pins_one_behind_the_other_in_one_bar_are_measured(seed):
    """Surgeon's views seeds 5 and 15: view 2 (-76, -89 deg) sees the pins one behind the
    other, their edges a few px apart: one bar 1.3 pins wide, which no split makes two
    pins of. The fit shares its edges out between the pins from the first solve, and the
    other view tells the pins apart (both were refused: "pin1 not told from the other pin")."""
    result = realism_case(("phantom", "views", seed, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "success", result


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize("seed", [16, 27])
def test_pins_in_a_plane_every_view_sees_edge_on_are_measured_however_turned(seed):
    """Surgeon's views seeds 16 and 27: an AP view sees the pins end to end on one line, a
    lateral view one behind the other. Their plane is that line seen from the source, but
    nothing shows how they turn within it: they come out 25-33 deg apart there, even
    solved from the truth. Both views within 1.5 deg of edge-on, their poses held to the
    encoders' motion, fix the plane, and the angles are right (refused before as not
    parallel)."""
    result = realism_case(("phantom", "views", seed, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "success", result


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize("scene_name", ["dose", "flat_panel"])
def test_pins_in_a_plane_both_views_see_edge_on_are_measured_despite_the_nuisance(scene_name):
    """Seed 16: both views see the pins' plane within 0.6 deg of edge-on; at low dose or on
    a flat panel the pins come out 3.2-3.8 deg apart within it, more than 4 times what the
    covariance says the views resolve of that turn, and the views' motion sits 4.1-4.3
    sigma RMS off the encoders'. Edge-on in every view, the turn is excused, and the angles
    are right within 0.2 deg (refused before)."""
    result = realism_case(("phantom", scene_name, 16, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "success", result


@pytest.mark.skipif(not (SHARED_DATA / "knee-smith2019" / "tibia-right.stl").is_file(),
                    reason="shared meshes absent")
def test_pins_turned_in_a_plane_one_view_sees_at_a_slant_are_not_measured():
    """The real tibia's surgeon's views seed 27: view 1 sees the pins' plane edge-on (0.6
    deg), view 2 2.0 deg off it, at a slant that resolves the pins' turn. Their 6.3 deg turn
    is not excused, and the case is refused (excused where one edge-on view sufficed, it
    was measured 0.88 deg off in STR)."""
    result = realism_case(("real", "views", 27, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "refused", result


def test_the_detectors_unsharpness_blurs_the_frame_and_leaves_the_other_draws(phantom_plan, scene):
    """The unsharpness nuisance draws the detector's blur (0.7-2.0 px) from the case's own
    stream after every other draw, so a scene with it differs from one without only in how
    sharp its frames are; seed 9 draws the most blur of seeds 0-29 (2.0 px), and its
    frames are measured."""
    blurred, sharp = OperatingRoom.only("unsharpness").draw(9), OperatingRoom().draw(9)
    assert blurred.detector_blur_px == pytest.approx(2.0, abs=0.01)
    assert blurred.flexion_deg == sharp.flexion_deg and blurred.photons == sharp.photons
    assert blurred.params(XRayParams()).detector_blur_px == blurred.detector_blur_px
    assert sharp.params(XRayParams()).detector_blur_px == XRayParams().detector_blur_px
    fine = []
    for room in (OperatingRoom(), OperatingRoom.only("unsharpness")):
        _, frames = _room_frames(phantom_plan, scene, room, 9)
        image = frames[0].radiograph.image[312:712, 312:712].astype(np.float32)  # inside the field
        fine.append(float(np.std(cv2.Laplacian(image, cv2.CV_32F))))
    assert fine[1] < 0.5 * fine[0]
    result = realism_case(("phantom", "unsharpness", 9, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "success", result


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_a_wrong_naming_in_a_plane_seen_edge_on_is_not_excused_its_turn():
    """Scatter seed 16: the pins' names in view 2 come out swapped, the views bent to fit
    them (E_odo 5.1 sigma RMS), so that view 2 sees the pins' plane 2.0 deg off edge-on: the
    pins' 3.4 deg turn within it is not excused, and the case is refused (excused where one
    edge-on view sufficed, its other naming was measured 1.07 deg off in STR)."""
    result = realism_case(("phantom", "scatter", 16, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "refused"
    assert "3.4 deg from parallel" in result["reason"]


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_pins_in_one_bar_too_short_for_them_are_refused_saying_so():
    """Operating-room seed 23: view 2 shows a bar two pins wide but shorter than the pins
    can be; it is not taken for them, and the refusal says what was seen."""
    result = realism_case(("phantom", "operating-room", 23, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "refused"
    assert ("view view2: pin1 not told from the other pin (one bar as wide as both: the pins "
            "lie one behind the other)") in result["reason"]


def test_pins_exactly_in_line_in_a_lateral_view_are_refused_saying_so():
    """Surgeon's views seed 19, view 2 (lateral, 68 deg): the pins lie in line, one behind
    the other, one bar a pin wide running out of the field. It is no pair, and halved it
    makes no two pins as long as a pin can be; the refusal says what was seen, not that no
    steel bar of a pin's shape was there."""
    result = realism_case(("phantom", "views", 19, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "refused"
    assert ("view view2: pin1 not told from the other pin (one bar a pin wide: the pins lie in "
            "line, one behind the other, or the other is hidden)") in result["reason"]


@pytest.mark.xfail(strict=True, reason="a known wrong answer, not yet refused: 2.2 deg off in CTR "
                                        "(docs/realism.md, thirty-third pass)")
def test_pins_one_behind_the_other_between_blades_are_not_measured_wrong():
    """Retractors with the surgeon's views, seed 8: in the lateral view the pins lie exactly
    one behind the other between two blades, a bar with no step. Cut in its middle, pin 1
    was given the back half only, slid 33 mm along its axis, and the case was measured 1.5
    deg off in CTR; pooled for the fit, pin 1 still slides 33 mm (the views turn with it,
    E_odo 5.6 sigma RMS, a reported sigma of 0.21 deg) and it is measured 2.2 deg off."""
    result = realism_case(("phantom", "retractors+views", 8, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] in ("refused", "success"), result


@pytest.mark.skipif(not (SHARED_DATA / "knee-smith2019" / "tibia-right.stl").is_file(),
                    reason="shared real tibia absent")
def test_retractor_blades_taken_for_the_pins_in_both_views_are_refused():
    """The real tibia, retractors and surgeon's views seed 14: two pieces of blades in each
    view triangulated to a parallel pair that fitted every gate, both 73-75 deg from the
    tibia's front-to-back axis, and the case was measured 4.9 deg off in STR."""
    result = realism_case(("real", "retractors+views", 14, (1,), str(SHARED_DATA)))["levels"][1]
    assert result["status"] == "refused"
    assert "from the tibia's front-to-back axis" in result["reason"]


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_a_dark_band_beside_a_pin_is_not_taken_for_its_edge(phantom_plan, scene):
    """Seed 0 of the processing scene, view 1: the sharpened plateau leaves a dark band
    40 px above pin 2, as steel-like as a pin; its outline was given to pin 2 (1163 edge
    points, the band's among them). Only the pair's own edges are the pins' now."""
    _, frames = _room_frames(phantom_plan, scene, OperatingRoom.only("processing", MESHES), 0)
    radiograph = frames[0].radiograph
    found = extract_contours(radiograph.image)
    for label in ("pin1", "pin2"):
        points = getattr(found, label)
        assert len(points) > 100
        assert np.max(cKDTree(radiograph.silhouettes[label]).query(points)[0]) < 10.0


def _labelled(radiograph, found) -> bool:
    """Each pin's edge points lie on its own true outline, nearer it than the other's."""
    truth = radiograph.silhouettes
    for own, other in (("pin1", "pin2"), ("pin2", "pin1")):
        points = getattr(found, own)
        if len(points) < 20:
            return False
        d_own, d_other = (float(np.median(cKDTree(truth[k]).query(points)[0])) for k in (own, other))
        if not (d_own < 2.0 and d_own < d_other):
            return False
    return True


def _retractors_pins(plan, scene, seed: int, view: int, room: OperatingRoom | None = None):
    """A retractors frame (or one of ``room``) and what is extracted from it with the plan's
    pins at the true pose."""
    room = room or OperatingRoom.only("retractors")
    frame = _room_frames(plan, scene, room, seed)[1][view]
    _, truth = _room_case(plan, room, seed)
    shadows = plan.pin_shadows(frame.radiograph.camera, truth.truth_T_cam_tibia[view],
                               truth.truth_T_tibia_pin)
    return frame, extract_contours(frame.radiograph.image,
                                   expected_pins=frame.radiograph.distortion.distort(shadows.centres),
                                   expected_pin_width_px=shadows.width_px,
                                   expected_pin_length_px=shadows.length_px)


@pytest.mark.parametrize("seed, view", [(1, 0), (2, 0), (3, 0), (4, 1)])
def test_pins_crossed_or_flanked_by_retractor_blades_are_found(phantom_plan, scene, seed, view):
    """Retractor blades seen edge-on are as straight as a pin. Seeds 1-3, view 1: a pin
    crosses one (one cross-shaped shadow, no pin-shaped candidate: the pins were lost, or
    blades taken for them); seed 3 and seed 4 view 2: a strip of a face-on blade, or two
    edge-on blades, were taken for the pins. With the plan's pin width at the pose, the
    shadow is cut into its straight bars and the pins are told from the blades."""
    frame, found = _retractors_pins(phantom_plan, scene, seed, view)
    assert _labelled(frame.radiograph, found)


@pytest.mark.parametrize("seed, view", [(2, 1), (9, 0), (16, 0), (22, 1)])
def test_pins_in_line_beside_a_blades_fold_or_across_three_blades_are_found(phantom_plan, scene,
                                                                             seed, view):
    """Both pins in line make one long shadow. Seeds 2, 9, 16: a bent blade's fold seen
    obliquely, as wide and straight as a pin but under a third of its length, was paired with
    that shadow as the pins; the plan's pin length at the pose rules it out. Seed 22 view
    2: the pins cross three blades and their shadow was smaller than the blades' strips,
    so it was never tried as the one that holds both pins."""
    frame, found = _retractors_pins(phantom_plan, scene, seed, view)
    assert _labelled(frame.radiograph, found)


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_parallel_pins_seen_nearly_end_on_converge_and_are_paired(phantom_plan, scene):
    """Operating-room seed 8, view 1 (7 deg): the pins, seen along ~20 deg of their axis,
    are short headed shadows 36 deg apart in direction, pointing at their vanishing point.
    No pair was parallel enough, and a retractor blade was split as the pins. Shadows that
    converge on one vanishing point, foreshortened alike, are the pair."""
    frame, found = _retractors_pins(phantom_plan, scene, 8, 0, OperatingRoom.everything(MESHES))
    assert found.diagnostics["pins_overlap"] == "apart"
    assert _labelled(frame.radiograph, found)


def test_pins_seen_end_on_as_stubs_are_paired(phantom_plan, scene):
    """Surgeon's views seed 24, view 1 (4 deg from AP): the pins cast pills 2.3 and 3.4
    widths long, 27 deg apart, 401 and 231 px from their vanishing point. The shorter was
    cut into a thinner piece and the pair was refused for unlike distances: neither pin was
    found."""
    frame, found = _retractors_pins(phantom_plan, scene, 24, 0, OperatingRoom.only("views"))
    assert found.diagnostics["pins_overlap"] == "apart"
    assert _labelled(frame.radiograph, found)


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_blade_pieces_that_converge_by_chance_are_not_taken_for_the_pins(phantom_plan, scene):
    """Operating-room seed 17, view 2: two pieces of retractor blades, pin-wide, 33 deg
    apart and foreshortened alike, but 1.7 times as far from where their axes meet: pins
    side by side at one depth are as far from their vanishing point. The pins are found."""
    frame, found = _retractors_pins(phantom_plan, scene, 17, 1, OperatingRoom.everything(MESHES))
    assert _labelled(frame.radiograph, found)


def test_the_field_is_found_when_blades_as_dark_as_no_signal_reach_its_rim(phantom_plan, scene):
    """Seed 1, view 2: two retractor blades run from the field's rim into it, as dark as
    the intensifier's no-signal surround. Their outlines made a third of the dark region's
    boundary: the circle fell below its inlier share, the frame was read as a flat panel of
    the wrong polarity and no pin was found."""
    _, frames = _room_frames(phantom_plan, scene, OperatingRoom.only("retractors"), 1)
    centre, radius, _, sign, _ = field_of_view(frames[1].radiograph.image, "auto")
    assert radius == pytest.approx(512.0, abs=2.0) and sign == 1


@pytest.mark.parametrize("seed, view", [(1, 1), (10, 1), (22, 1)])
def test_a_pins_edges_over_a_face_on_blade_are_kept(phantom_plan, scene, seed, view):
    """A pin across face-on blades kept its edges only beside them (41-46% of its outline
    within 2 px), and came out 5-6 deg from parallel to the other: 2 mm of steel passes
    quanta, so its edges over a blade are placed as over tissue."""
    frame, found = _retractors_pins(phantom_plan, scene, seed, view)
    assert _labelled(frame.radiograph, found)
    outline = frame.radiograph.silhouettes["pin1"]
    assert np.mean(cKDTree(found.pin1).query(outline)[0] <= 2.0) >= 0.6
@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_tissue_that_a_femur_cuts_off_from_the_skin_is_not_taken_for_bone(phantom_plan, scene):
    """The femur closes the joint space above the plateau and the leg fills the field beside
    the fibula: the tissue there is reached from no skin. It lies below the bones around it,
    so it is tissue, and most of the outline beside it is found (72%; it was 43%,
    and the case was refused)."""
    _, frames = _room_frames(phantom_plan, scene, OperatingRoom.only("femur", MESHES), 0)
    frame = frames[0]
    assert _scores(frame, extract_contours(frame.radiograph.image))["coverage"] > 0.65


def test_a_low_dose_bone_edge_the_mask_misses_is_sought_near_the_model():
    """Dose seed 4, view 2: at low dose the soft tissue reaches past the tibia's gently
    rising edge and the bone mask's boundary lies 10-20 px inside it; the bone stage ended
    16 px off its contour and the case was refused. The edges sought near the model's
    outline put it right."""
    row = realism_case(("phantom", "dose", 4, (1,), str(SHARED_DATA)))
    assert row["levels"][1]["status"] == "success", row["levels"][1]


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_a_wrong_pose_that_edges_sought_near_it_would_confirm_is_never_measured():
    """Femur seed 24, with edges sought from as far as 40 px: those found near a view 7 deg
    off fitted it (median 1.2 px) and the case was measured 16 deg off in CTR; the gate on
    the share of the outline the frame shows an edge along refused it (a third of that
    view's outline). Since the edges are sought from the alignment's poses first (issue 26,
    eleventh pass) the bone stage finds the tibia there and the case is measured right;
    whichever way, never wrong (the gate itself: test_solver)."""
    wide = SolverConfig(schedule=ScheduleConfig(bone_edge_reach_px=(40.0, 16.0, 8.0, 4.0)))
    row = realism_case(("phantom", "femur", 24, (1,), str(SHARED_DATA)), wide)
    assert row["levels"][1]["status"] in ("success", "refused"), row["levels"][1]


def _under_shutters(draw, points: np.ndarray, size: int) -> np.ndarray:
    """Which points (raw px of a flat-panel frame) lie behind the draw's collimator blades."""
    under = np.zeros(len(points), bool)
    for side, depth, tilt in draw.shutters:
        across, along = (points[:, 0], points[:, 1]) if side in (0, 2) else (points[:, 1], points[:, 0])
        edge = depth * size + np.tan(np.radians(tilt)) * (along - size / 2)
        under |= across < edge if side in (0, 1) else across > size - edge
    return under


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_no_bone_edge_is_kept_behind_a_faint_collimator_shutter(phantom_plan, scene):
    """A flat panel with scatter and a log response leaves the top shutter too faint to be
    opaque (seed 22, all nuisances): at low dose its noise gave ~1,000 bone edge points
    behind the blade (a fifth of the contour), and the bone stage ended 10-40 deg off. The
    blade's straight edge across the field, with nothing clearer beyond it, marks it."""
    draw, frames = _room_frames(phantom_plan, scene, OperatingRoom.everything(MESHES), 22)
    frame = frames[0]
    found = extract_contours(frame.radiograph.image)
    assert found.diagnostics["shutters"] == 1
    assert not _under_shutters(draw, found.bone, frame.radiograph.image.shape[1]).any()


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize("seed, view", [(10, 0), (20, 0), (27, 0), (28, 0)])
def test_pins_of_a_processed_frame_are_found_and_named(phantom_plan, scene, seed, view):
    """Processing scene, view 1. Seeds 10 and 27: the C-arm's window clipped both pins,
    in line, to its darkest level, so their excess over the tissue below was 0.3-0.5 and
    one pin was never seeded (the other was split in two as both pins). Seed 28: the window
    clipped one pin's end, whose peak (8.7) left the other pin (3.4) under half of it.
    Seed 20: the dark bands that unsharp masking leaves along the plateau were paired as
    the pins; their sides follow the plateau's curve, a pin's are straight."""
    frame, found = _retractors_pins(phantom_plan, scene, seed, view,
                                    OperatingRoom.only("processing", MESHES))
    assert _labelled(frame.radiograph, found)


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_a_band_along_a_shutters_edge_is_not_taken_for_the_pins(phantom_plan, scene):
    """Operating-room seed 6, view 1: the C-arm's edge enhancement leaves a dark band along
    the left shutter's edge, straight and a pin wide, under the shutter. It was split as
    both pins while the pins, in line across a blade, were lost."""
    room = OperatingRoom.everything(MESHES)
    draw, _ = _room_case(phantom_plan, room, 6)
    frame, found = _retractors_pins(phantom_plan, scene, 6, 0, room)
    assert found.diagnostics["shutters"] == 1
    assert _labelled(frame.radiograph, found)
    width = frame.radiograph.image.shape[1]
    assert not any(_under_shutters(draw, pin, width).any() for pin in (found.pin1, found.pin2))


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_pins_beside_a_blade_seen_edge_on_pass_as_steel(phantom_plan, scene):
    """Operating-room seed 25, view 1 (inverted, processed): a retractor blade seen edge-on
    in the frame's corner has a typical excess of 4.9, the pins 1.8; under half of the
    strongest bar's, the pins were dropped with the bone's bars and none was found."""
    frame, found = _retractors_pins(phantom_plan, scene, 25, 0, OperatingRoom.everything(MESHES))
    assert found.diagnostics["pins_overlap"] == "apart"
    assert _labelled(frame.radiograph, found)


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
def test_headed_pins_pass_as_straight_bars(phantom_plan, scene):
    """Headed pins scene, seed 0 view 1: a head wider than the shaft steps both sides of
    a pin's shadow out near one end; the shadow is still a pin's (straight sides), not a
    sharpened bone edge's band. A line fitted to all of a side was tilted by the head
    (2.5 px median off), and one pin was lost."""
    frame, found = _retractors_pins(phantom_plan, scene, 0, 0, OperatingRoom.only("headed_pins", MESHES))
    assert found.diagnostics["pins_overlap"] == "apart"
    assert _labelled(frame.radiograph, found)


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize("nuisance, seed, view, overlap", [(None, 25, 1, "apart"), ("retractors", 12, 1, "apart"),
                                                           ("headed_pins", 7, 1, "apart"),
                                                           ("headed_pins", 16, 0, "staggered")])
def test_pins_touching_side_by_side_or_headed_in_line_are_told_apart(phantom_plan, scene, nuisance, seed,
                                                                      view, overlap):
    """View 2 of idealised seed 25 and retractors seed 12: the pins touch side by side in a
    slit a pixel or two wide; headed pins seed 7: 8 px apart, one's head touching the
    other's shaft. One shadow notched by the slit, it was split as pins in line, one pin
    cut to half its length or less. Headed pins seed 16, view 1: pins in line, offset
    across; the second pin's head stands out of one side of their shadow only, the
    first's (at its end) out of its own side by less than the second pin's side lies
    beyond it. Both heads were read as steps and the first pin cut at the second's head: a
    third of its true outline was found (now three fifths: its shaft's, not its head's)."""
    room = OperatingRoom.only(nuisance, MESHES) if nuisance else OperatingRoom()
    frame, found = _retractors_pins(phantom_plan, scene, seed, view, room)
    assert found.diagnostics["pins_overlap"] == overlap
    assert _labelled(frame.radiograph, found)
    for label in ("pin1", "pin2"):
        truth = frame.radiograph.silhouettes[label]
        assert np.mean(cKDTree(getattr(found, label)).query(truth)[0] <= 3.0) > 0.5


@pytest.mark.skipif(not (MESHES / "femur-generic-right.stl").is_file(), reason="shared meshes absent")
@pytest.mark.parametrize("seed", [22, 27])
def test_headed_pins_in_line_are_measured(seed):
    """Headed pins seeds 22 and 27: in one view the pins lie in line, one overlapping the
    other, and a head stands out of both sides of their one shadow (on its end, or on the
    other pin's shaft). Read as a step between the pins, it cut the split wrong: seed 27 was
    refused as "one bar a pin wide", seed 22 as "the two pins lie one behind the other"."""
    row = realism_case(("phantom", "headed_pins", seed, (1,), str(SHARED_DATA)))
    assert row["levels"][1]["status"] == "success", row["levels"][1]


@pytest.mark.parametrize("seed, view", [(1, 0), (10, 1), (11, 1)])
def test_a_pin_whose_excess_dips_beside_the_air_is_found_whole(phantom_plan, scene, seed, view):
    """Scatter scene. Behind steel the detector sees the scatter, high beside the air by
    the leg: there a pin's excess dipped under half its peak and its shadow was cut in two,
    the shorter piece left out (a quarter to a half of its outline found; the case refused).
    The pieces in line, with a bar between them, are one shadow again."""
    frame, found = _retractors_pins(phantom_plan, scene, seed, view, OperatingRoom.only("scatter", MESHES))
    assert _labelled(frame.radiograph, found)
    for label in ("pin1", "pin2"):
        truth = frame.radiograph.silhouettes[label]
        assert np.mean(cKDTree(getattr(found, label)).query(truth)[0] <= 3.0) > 0.55
