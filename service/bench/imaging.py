"""``slamtka bench imaging --out DIR``: figures of the imaging chain on simulated data.

- rendering: seconds per 1024 x 1024 radiograph (the first frame also builds the distortion
  maps, which a C-arm keeps; it is reported apart);
- calibration: simulated phantom sets (random true principal point and focal length, the
  default intensifier distortion): focal length error (%), principal point error (px),
  residual distortion after correction (RMS px over the field of what no pinhole explains), share of images whose grid was found;
- calibration on real-world sets (plate error 0.1-0.3 mm, specks, missing balls, an empty
  frame, a duplicate): share of the frames showing the grid that were used, whether the
  empty frame and the duplicate were set aside, focal length error, principal point error
  where the set determines it, final RMS over the noise floor (over the frames used in both:
  the floor is the RMS of the same frames, same poses and noise, of a perfect plate
  calibrated without refining the plate, scaled for the plate's extra parameters);
- contours: distances of extracted bone edge points to the true outline (median, p95, px),
  share of the visible true outline within 2 px of an extracted point (coverage; visible:
  inside the field margin and outside the pins' shadows), pins found and correctly
  labelled, extraction seconds per frame;
- end to end: frames -> contours -> undistortion -> ``solve_joint`` at initial-noise
  levels of docs/evaluation.md: absolute CTR/STR errors.

Prints a summary and writes ``imaging.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
from scipy.spatial import cKDTree

from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.plate_images import (
    PhantomSet,
    plate_offsets,
    simulate_phantom_images,
    simulate_phantom_set,
)
from slamtka.sim.simulate import (
    DETECTOR_FIELD_MM,
    ROT_SD_PER_LEVEL_RAD,
    TRANS_SD_PER_LEVEL_MM,
    SimulationConfig,
    default_camera,
    simulate_case,
)
from slamtka.sim.xray import Radiograph, XRayParams, XRayScene, default_distortion, render_radiograph
from slamtka.solver.camera import Camera
from slamtka.solver.imaging.calibration import CalibrationImage, CalibrationOptions, calibrate
from slamtka.solver.imaging.contours import ContourConfig, ExtractedContours, extract_contours
from slamtka.solver.imaging.distortion import Distortion
from slamtka.solver.imaging.plate import PhantomSpec
from slamtka.solver.slam import SolverConfig, solve_joint

__all__ = ["contour_scores", "residual_distortion_px", "add_imaging_bench_parser", "run_imaging"]

Result = TypeVar("Result")

COVERED_PX = 2.0
PIN_SHADOW_PX = 16.0  # true bone outline this close to a pin's outline lies in its shadow
PIN_FOUND_PX = 2.0


def contour_scores(radiograph: Radiograph, found: ExtractedContours,
                   config: ContourConfig = ContourConfig()) -> dict:
    """Bone distances and coverage, and whether both pins were found with the right labels."""
    truth = radiograph.silhouettes
    camera = radiograph.camera
    bone_truth = truth["bone"][camera.in_field(truth["bone"], config.fov_margin_px)]
    pins = np.vstack([truth["pin1"], truth["pin2"]])
    if len(pins):
        bone_truth = bone_truth[cKDTree(pins).query(bone_truth)[0] > PIN_SHADOW_PX]
    scores = {"bone_points": len(found.bone), "distances": np.zeros(0), "coverage": 0.0}
    if len(found.bone) and len(bone_truth):
        scores["distances"] = cKDTree(bone_truth if len(bone_truth) else truth["bone"]).query(found.bone)[0]
        scores["coverage"] = float(np.mean(cKDTree(found.bone).query(bone_truth)[0] <= COVERED_PX))
    labelled = True
    for own, other in (("pin1", "pin2"), ("pin2", "pin1")):
        points = getattr(found, own)
        if len(points) == 0 or len(truth[own]) == 0:
            labelled = False
            continue
        d_own = float(np.median(cKDTree(truth[own]).query(points)[0]))
        d_other = float(np.median(cKDTree(truth[other]).query(points)[0]))
        labelled &= d_own <= PIN_FOUND_PX and d_own < d_other
    scores["pins_labelled"] = bool(labelled)
    return scores


def residual_distortion_px(true_camera: Camera, true_distortion: Distortion,
                           distortion: Distortion, margin_px: float = 10.0) -> float:
    """RMS (px) of what the estimated correction leaves of the true distortion over the field.

    Ideal points of the true camera are distorted by the true intensifier and corrected with
    the estimate; what no pinhole camera explains (the residual of the best projective map
    from the ideal to the corrected points) is the residual distortion. A principal point or
    focal length difference is a different pinhole, reported apart.
    """
    u, v = np.meshgrid(np.linspace(0, true_camera.width - 1, 60), np.linspace(0, true_camera.height - 1, 60))
    ideal = np.column_stack([u.ravel(), v.ravel()])
    observed = true_distortion.distort(ideal)
    inside = true_camera.in_field(observed, margin_px)
    ideal, corrected = ideal[inside], distortion.undistort(observed[inside])
    H, _ = cv2.findHomography(ideal, corrected, 0)
    mapped = cv2.perspectiveTransform(ideal[None].astype(np.float64), H)[0]
    return float(np.sqrt(np.mean(np.sum((corrected - mapped) ** 2, axis=1))))


def _true_camera(nominal: Camera, rng: np.random.Generator) -> Camera:
    """A C-arm of the nominal kind: focal length within 3%, principal point within 10 px."""
    f = nominal.fx * rng.uniform(0.97, 1.03)
    return Camera(f, f, nominal.cx + rng.uniform(-10, 10), nominal.cy + rng.uniform(-10, 10),
                  nominal.width, nominal.height, nominal.fov_radius_px)


def _calibration_study(sets: int, images: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    nominal = default_camera()
    spacing = DETECTOR_FIELD_MM / nominal.width
    rows = []
    for _ in range(sets):
        true = _true_camera(nominal, rng)
        distortion = default_distortion(true)
        phantom = simulate_phantom_images(true, distortion, PhantomSpec(), images, rng)
        calibration, report = calibrate([CalibrationImage(f"img{i:02d}", image, (spacing, spacing), 1000.0)
                                         for i, image in enumerate(phantom)])
        c = calibration.camera
        rows.append({
            "focal_error_pct": 100.0 * abs(c.fx / true.fx - 1.0),
            "principal_point_error_px": float(np.hypot(c.cx - true.cx, c.cy - true.cy)),
            "residual_distortion_rms_px": residual_distortion_px(true, distortion, calibration.distortion),
            "grid_found_pct": 100.0 * report["used"] / images,
            "reprojection_rms_px": report["rms_px"],
            "principal_point_held": report["principal_held"]})
    return {"sets": rows, "images_per_set": images,
            **{f"max_{k}": max(r[k] for r in rows) for k in
               ("focal_error_pct", "principal_point_error_px", "residual_distortion_rms_px")},
            "min_grid_found_pct": min(r["grid_found_pct"] for r in rows)}


def _shows_grid(phantom: PhantomSet, name: str, camera: Camera, distortion: Distortion,
                spec: PhantomSpec, min_balls: int) -> bool:
    """Whether a frame shows enough balls of the plate, clear of the field's rim and of the
    clamp's shadow, to be used."""
    seen = ~np.isnan(phantom.plate_mm[:, 0])
    seen[phantom.under_clamp.get(name, [])] = False
    plate = phantom.plate_mm[seen]
    uv = distortion.distort(camera.project(phantom.poses[name].apply(plate)))
    ball_px = spec.ball_diameter_mm * camera.fx / phantom.poses[name].t[2]
    return int(camera.in_field(uv, ball_px + 3.0).sum()) >= min_balls


def _noise_floor(report: dict, twin: dict) -> tuple[float, float]:
    """The calibration's RMS (px) and its noise floor, over the frames both runs used.

    ``twin``: the report of the same frames (same poses, noise drawn alike) of a perfect plate,
    calibrated without refining the plate: what the camera model leaves of detection noise.
    The floor is its RMS scaled by sqrt((2n - p) / (2n - p_twin)) for the plate's extra
    parameters, which take up part of the noise in the real run's fit."""
    def over_common(doc: dict, other: dict) -> float:
        theirs = {e["image"] for e in other["images"] if e["used"]}
        mine = [e for e in doc["images"] if e["used"] and e["image"] in theirs]
        balls = sum(e["balls_used"] for e in mine)
        return float(np.sqrt(sum(e["balls_used"] * e["rms_px"] ** 2 for e in mine) / balls))

    rms, floor = over_common(report, twin), over_common(twin, report)
    dof_real = 2 * report["observations"] - report["parameters"]
    dof_twin = 2 * twin["observations"] - twin["parameters"]
    return rms, floor * float(np.sqrt(dof_real / dof_twin))


def _real_world_study(sets: int, images: int, seed: int) -> dict:
    """Sets as a hospital collects them: plate error 0.1-0.3 mm, two specks per frame (one
    continuing the grid), one or two balls missing, an empty frame and a duplicate."""
    rng = np.random.default_rng(seed + 1000)
    nominal = default_camera()
    spacing = DETECTOR_FIELD_MM / nominal.width
    spec, options = PhantomSpec(), CalibrationOptions()
    rows = []
    for _ in range(sets):
        true = _true_camera(nominal, rng)
        distortion = default_distortion(true)
        plate_error = float(rng.uniform(0.1, 0.3))
        missing = tuple(int(i) for i in rng.choice(spec.rows * spec.cols, int(rng.integers(1, 3)), replace=False))
        offsets = plate_offsets(spec, plate_error, rng)
        state = rng.bit_generator.state
        runs = {}
        for kind, plate, how in (("real", offsets, options), ("twin", None, replace(options, refine_plate=False))):
            rng.bit_generator.state = state  # the same poses and noise, with and without the error
            phantom = simulate_phantom_set(true, distortion, spec, images, rng, plate, missing_balls=missing,
                                           specks=2, empty_frames=1, duplicates=1)
            runs[kind] = phantom, calibrate([CalibrationImage(n, image, (spacing, spacing), 1000.0)
                                             for n, image in zip(phantom.names, phantom.images)], spec, how)
        phantom, (calibration, report) = runs["real"]
        rms, floor = _noise_floor(report, runs["twin"][1][1])
        c = calibration.camera
        entries = {e["image"]: e for e in report["images"]}
        showing = [n for n in phantom.poses if _shows_grid(phantom, n, true, distortion, spec, options.min_balls)]
        held = report["principal_held"]
        rows.append({
            "plate_error_true_mm": plate_error, "missing_balls": len(missing),
            "plate_error_estimated_rms_mm": report["plate"]["error_rms_mm"],
            "grid_used_pct": 100.0 * sum(entries[n]["used"] for n in showing) / max(len(showing), 1),
            "frames_showing_grid": len(showing),
            "set_aside_right": all(not entries[n]["used"] for n in phantom.notes),
            "outlier_balls": sum(len(e["outlier_balls"]) for e in report["images"]),
            "focal_error_pct": 100.0 * abs(c.fx / true.fx - 1.0),
            "principal_point_error_px": None if held else float(np.hypot(c.cx - true.cx, c.cy - true.cy)),
            "principal_point_held": held,
            "not_used_showing_grid": {n: entries[n]["reason"] for n in showing if not entries[n]["used"]},
            "rms_px": report["rms_px"], "rms_common_frames_px": rms, "noise_floor_px": floor,
            "rms_over_floor": rms / floor})
    estimable = [r["principal_point_error_px"] for r in rows if r["principal_point_error_px"] is not None]
    return {"sets": rows, "images_per_set": images,
            "min_grid_used_pct": min(r["grid_used_pct"] for r in rows),
            "empty_and_duplicate_set_aside": all(r["set_aside_right"] for r in rows),
            "max_focal_error_pct": max(r["focal_error_pct"] for r in rows),
            "max_principal_point_error_px": max(estimable) if estimable else None,
            "principal_point_held_sets": sum(r["principal_point_held"] for r in rows),
            "max_rms_over_floor": max(r["rms_over_floor"] for r in rows)}


def _timed(wall: list[float], cpu: list[float], fn: Callable[..., Result], *args) -> Result:
    """``fn(*args)``, appending its wall-clock and process CPU seconds (the CPU figure is what
    the step costs itself on a machine shared with other work)."""
    start, start_cpu = time.perf_counter(), time.process_time()
    result = fn(*args)
    wall.append(time.perf_counter() - start)
    cpu.append(time.process_time() - start_cpu)
    return result


def run_imaging(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    plan = phantom_plan()
    plan.bone_model()
    plan.pin_model()
    camera = default_camera()
    params = XRayParams()
    scene = XRayScene.from_plan(plan, params)
    config = ContourConfig()
    render_s, extract_s, distances, coverage, pins_ok = [], [], [], [], []
    render_cpu_s, extract_cpu_s = [], []
    e2e = {level: {"ctr_abs_deg": [], "str_abs_deg": [], "refused": []} for level in args.levels}
    for case_index in range(args.cases):
        seed = args.seed + case_index
        sim = simulate_case(plan, SimulationConfig(seed=seed))
        raw = []
        for T in sim.truth_T_cam_tibia:
            radiograph = _timed(render_s, render_cpu_s, render_radiograph, plan, T, sim.truth_T_tibia_pin,
                                camera, params, np.random.default_rng(seed), scene)
            found = _timed(extract_s, extract_cpu_s, extract_contours, radiograph.image, config)
            scores = contour_scores(radiograph, found, config)
            distances.append(scores["distances"])
            coverage.append(scores["coverage"])
            pins_ok.append(scores["pins_labelled"])
            raw.append((radiograph, found))
        for level in args.levels:
            case = simulate_case(plan, SimulationConfig.at_level(level, seed))
            views = [f.observation(v.view_id, camera, r.distortion.undistort, r.distortion.distort)
                     for v, (r, f) in zip(case.views, raw)]
            outcome = solve_joint(plan, views, case.initial, SolverConfig())
            if outcome.status == "measured":
                e2e[level]["ctr_abs_deg"].append(abs(float(np.degrees(outcome.plane.ctr)) - case.truth_ctr_deg))
                e2e[level]["str_abs_deg"].append(abs(float(np.degrees(outcome.plane.str_)) - case.truth_str_deg))
            else:
                e2e[level]["refused"].append(outcome.reason)
        print(f"  case {case_index + 1}/{args.cases} done", flush=True)
    all_d = np.concatenate(distances) if distances else np.zeros(0)
    results = {
        "rendering": {"frames": len(render_s), "first_s": render_s[0] if render_s else None,
                      "median_s": float(np.median(render_s[1:] or render_s)),
                      "max_s": float(np.max(render_s[1:] or render_s)),
                      "cpu_median_s": float(np.median(render_cpu_s[1:] or render_cpu_s))},
        "contours": {"frames": len(coverage), "median_px": float(np.median(all_d)),
                     "p95_px": float(np.percentile(all_d, 95)),
                     "coverage_median": float(np.median(coverage)), "coverage_min": float(np.min(coverage)),
                     "pins_found_labelled_pct": 100.0 * float(np.mean(pins_ok)),
                     "extraction_median_s": float(np.median(extract_s)), "extraction_max_s": float(np.max(extract_s)),
                     "extraction_cpu_median_s": float(np.median(extract_cpu_s))},
        "calibration": (_calibration_study(args.calibration_sets, args.calibration_images, args.seed)
                        if args.calibration_sets else None),
        "calibration_real_world": (_real_world_study(args.real_world_sets, args.calibration_images, args.seed)
                                   if args.real_world_sets else None),
        "end_to_end": {str(level): {
            "rot_sd_rad": ROT_SD_PER_LEVEL_RAD * level, "trans_sd_mm": TRANS_SD_PER_LEVEL_MM * level,
            "cases": args.cases, "measured": len(r["ctr_abs_deg"]),
            "median_ctr_abs_deg": float(np.median(r["ctr_abs_deg"])) if r["ctr_abs_deg"] else None,
            "median_str_abs_deg": float(np.median(r["str_abs_deg"])) if r["str_abs_deg"] else None,
            "p95_ctr_abs_deg": float(np.percentile(r["ctr_abs_deg"], 95)) if r["ctr_abs_deg"] else None,
            "p95_str_abs_deg": float(np.percentile(r["str_abs_deg"], 95)) if r["str_abs_deg"] else None,
            "refusals": r["refused"]} for level, r in e2e.items()},
    }
    (args.out / "imaging.json").write_text(json.dumps(results, indent=2))
    print(_summary(results))
    return 0


def _summary(r: dict) -> str:
    rd, c, cal, real = r["rendering"], r["contours"], r["calibration"], r["calibration_real_world"]
    lines = [
        f"rendering: median {rd['median_s']:.2f} s, max {rd['max_s']:.2f} s per 1024x1024 frame "
        f"(CPU median {rd['cpu_median_s']:.2f} s; first frame {rd['first_s']:.2f} s incl. distortion maps), "
        f"{rd['frames']} frames",
        f"contours: {c['frames']} frames: bone edge distance median {c['median_px']:.2f} px, p95 "
        f"{c['p95_px']:.2f} px, coverage median {100 * c['coverage_median']:.1f}% (min "
        f"{100 * c['coverage_min']:.1f}%), pins found and labelled {c['pins_found_labelled_pct']:.0f}%, "
        f"extraction median {c['extraction_median_s']:.2f} s (max {c['extraction_max_s']:.2f} s, CPU median "
        f"{c['extraction_cpu_median_s']:.2f} s)",
    ]
    if cal is not None:
        lines.append(
            f"calibration: {len(cal['sets'])} sets x {cal['images_per_set']} images: focal error max "
            f"{cal['max_focal_error_pct']:.3f}%, principal point error max {cal['max_principal_point_error_px']:.2f} px, "
            f"residual distortion max {cal['max_residual_distortion_rms_px']:.3f} px RMS, grid found min "
            f"{cal['min_grid_found_pct']:.0f}%")
    if real is not None:
        pp = real["max_principal_point_error_px"]
        lines.append(
            f"calibration, real-world sets: {len(real['sets'])} sets x {real['images_per_set']} images (+ an empty "
            f"frame and a duplicate; plate error 0.1-0.3 mm, specks, missing balls): grid used in "
            f"{real['min_grid_used_pct']:.0f}% (min) of the frames showing it, empty and duplicate set aside: "
            f"{'yes' if real['empty_and_duplicate_set_aside'] else 'NO'}, focal error max "
            f"{real['max_focal_error_pct']:.3f}%, principal point error max "
            f"{'n/a' if pp is None else f'{pp:.2f} px'} ({real['principal_point_held_sets']} sets held it), "
            f"final RMS / noise floor max {real['max_rms_over_floor']:.2f}")

    def fmt(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.3f}"

    for level, e in r["end_to_end"].items():
        lines.append(f"end to end, level {level} (rot SD {e['rot_sd_rad']:.1f} rad, trans SD "
                     f"{e['trans_sd_mm']:.0f} mm): {e['measured']}/{e['cases']} measured, median |CTR| "
                     f"{fmt(e['median_ctr_abs_deg'])} deg, median |STR| {fmt(e['median_str_abs_deg'])} deg "
                     f"(p95 {fmt(e['p95_ctr_abs_deg'])} / {fmt(e['p95_str_abs_deg'])})")
    return "\n".join(lines)


def add_imaging_bench_parser(kinds: argparse._SubParsersAction) -> None:
    p = kinds.add_parser("imaging", help="rendering, calibration, contour and end-to-end figures")
    p.add_argument("--cases", type=int, default=10, help="simulated cases (two frames each)")
    p.add_argument("--levels", type=lambda s: [int(x) for x in s.split(",")], default=[1, 2],
                   help="initial-noise levels for the end-to-end solves")
    p.add_argument("--calibration-sets", type=int, default=3)
    p.add_argument("--calibration-images", type=int, default=16)
    p.add_argument("--real-world-sets", type=int, default=3,
                   help="simulated real-world phantom sets (plate error, specks, missing balls, ...)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.set_defaults(func=run_imaging)
