"""``slamtka bench realism --out DIR``: the imaging chain on operating-room frames.

For each scene (the idealised control, each nuisance of
:mod:`solver.imaging.operating_room` alone, and all of them at once) and each model (the
phantom and, when the shared data is there, the real tibia), ``--cases`` simulated cases
are rendered, their contours extracted (pin labels from the initial poses, as the service
does) and solved at each initial-noise level. Per scene and model: bone edge distance to
the true outline (median, p95, px), coverage of the visible true outline (not behind a
foreign body, a shutter or the marker) within 2 px, pins found and labelled, end-to-end
success (both angles within 1 deg), wrong angles (measured, more than 1 deg off), refusals
with their reasons, seconds of extraction per frame.

Writes ``results.json``, ``results.md`` and ``montage.png`` (the first frame of each scene
with its extracted contours: bone green, pin 1 red, pin 2 blue) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import re
import time
import traceback
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from slamtka.bench.args import names_from
from slamtka.bench.imaging import COVERED_PX, contour_scores
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.operating_room import (
    NUISANCES,
    OperatingRoom,
    RoomFrame,
    render_room,
    room_bodies,
    room_scene,
    view_angles,
)
from slamtka.sim.simulate import SimulationConfig, SimulationError, default_camera, simulate_case
from slamtka.sim.xray import XRayParams, XRayScene
from slamtka.solver.imaging.contours import (
    ContourConfig,
    ContourError,
    ExtractedContours,
    agreed_polarity,
    extract_contours,
)
from slamtka.solver.observations import ViewObservation
from slamtka.solver.plan import PinShadows, Plan
from slamtka.solver.slam import SolverConfig, solve_joint

__all__ = ["add_realism_bench_parser", "run_realism", "realism_case", "SHARED_DATA"]

SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
SUCCESS_DEG = 1.0
_DEFAULT_VIEWS = (-30.0, 30.0)

_plans: dict[str, Plan] = {}
_xray_scenes: dict[str, XRayScene] = {}


def _plan(model: str, data: Path) -> Plan:
    if model not in _plans:
        if model == "phantom":
            plan = phantom_plan("right")
        else:
            # The shared fibula is not a closed surface, which X-ray path lengths need: the
            # real model is its tibia alone (the plan as the frames: no fibula in either).
            smith = data / "knee-smith2019"
            landmarks = Path(__file__).resolve().parents[2] / "tests" / "data" / "knee-smith2019-landmarks.json"
            plan = Plan.from_meshes(smith / "tibia-right.stl", None, landmarks)
        plan.bone_model()
        plan.pin_model()
        _plans[model] = plan
        _xray_scenes[model] = XRayScene.from_plan(plan)
    return _plans[model]


def _room(scene: str, data: Path) -> OperatingRoom:
    """The scene's nuisances: ``idealised``, ``operating-room`` (all), or nuisances joined by
    ``+`` (``femur+retractors``: which combination breaks what)."""
    meshes = data / "knee-nuisance"
    if scene == "idealised":
        return OperatingRoom(mesh_folder=meshes)
    if scene == "operating-room":
        return OperatingRoom.everything(meshes)
    return OperatingRoom.of(scene.split("+"), meshes)


def _expected_pins(case, k: int, frame: RoomFrame, plan: Plan) -> PinShadows:
    """The pins' shadows at the initial poses (what the service labels pins by), with their
    centres distorted as the frame is."""
    shadows = plan.pin_shadows(frame.radiograph.camera, case.initial.T_cam_tibia[k],
                               case.initial.T_tibia_pin)
    return shadows._replace(centres=frame.radiograph.distortion.distort(shadows.centres))


def _scores(frame: RoomFrame, found: ExtractedContours) -> dict:
    """Bone distances, coverage of the visible true outline, pins found and labelled."""
    scores = contour_scores(frame.radiograph, found)
    truth = frame.radiograph.silhouettes["bone"]
    visible = truth[~frame.hidden["bone"]] if len(truth) else truth
    camera = frame.radiograph.camera
    visible = visible[camera.in_field(visible, 8.0)] if len(visible) else visible
    if len(found.bone) and len(visible):
        scores["coverage"] = float(np.mean(cKDTree(found.bone).query(visible)[0] <= COVERED_PX))
    elif len(visible):
        scores["coverage"] = 0.0
    else:
        scores["coverage"] = float("nan")
    return scores


def realism_case(job: tuple[str, str, int, tuple[int, ...], str], config: SolverConfig = SolverConfig()) -> dict:
    """One case of one scene and model: its frames' scores and its solve at every level; a
    defect is recorded with its place (one case cannot sink the study)."""
    try:
        return _realism_case(job, config)
    except Exception as exc:
        where = traceback.extract_tb(exc.__traceback__)[-1]
        model, scene, seed, levels, _ = job
        reason = f"{type(exc).__name__}: {exc} ({where.filename}:{where.lineno})"
        return {"model": model, "scene": scene, "seed": seed, "frames": [],
                "levels": {level: {"status": "error", "reason": reason} for level in levels}}


def _realism_case(job: tuple[str, str, int, tuple[int, ...], str], config: SolverConfig) -> dict:
    model, scene, seed, levels, data = job
    data_path = Path(data)
    row: dict = {"model": model, "scene": scene, "seed": seed, "frames": [], "levels": {}}
    try:
        plan = _plan(model, data_path)
        room = _room(scene, data_path)
        draw = room.draw(seed)
        angles = view_angles(draw, _DEFAULT_VIEWS)
        truth_case = simulate_case(plan, SimulationConfig(seed=seed, view_angles_deg=angles))
        cases = {level: simulate_case(plan, SimulationConfig(
            seed=seed, view_angles_deg=angles, init_rot_sd_rad=0.1 * level,
            init_trans_sd_mm=20.0 * level)) for level in levels}
    except SimulationError as exc:
        row["skipped"] = f"seed {seed}: {exc}"
        return row
    camera = default_camera()
    scene_model = room_scene(_xray_scenes[model], draw)
    bodies = room_bodies(plan, draw)
    frames = []
    rng = np.random.default_rng(seed)
    for T in truth_case.truth_T_cam_tibia:
        frames.append(render_room(plan, T, truth_case.truth_T_tibia_pin, camera, XRayParams(), draw, rng,
                                  scene_model, bodies))
    row["view_angles_deg"] = list(angles)
    for level, case in cases.items():
        views: list[ViewObservation] = []
        extracted = [_extracted(frame, _expected_pins(case, k, frame, plan)) for k, frame in enumerate(frames)]
        polarity = agreed_polarity([found for found, _, _ in extracted])
        if polarity is not None:  # as the service does (Pipeline._contours)
            extracted = [_again_as(polarity, frame, _expected_pins(case, k, frame, plan), first)
                         for k, (frame, first) in enumerate(zip(frames, extracted))]
        refusal = next((f"view {k + 1}: {error}" for k, (_, error, _) in enumerate(extracted) if error), None)
        for k, (frame, (found, _, seconds)) in enumerate(zip(frames, extracted)):
            if level == levels[0]:
                entry = {"seconds": seconds, "refused": found is None}
                if found is not None:
                    s = _scores(frame, found)
                    entry.update(median_px=float(np.median(s["distances"])) if len(s["distances"]) else None,
                                 distances=np.round(s["distances"], 2).tolist(), coverage=s["coverage"],
                                 pins_labelled=s["pins_labelled"])
                    if k == 0:
                        row["montage"] = {"image": frame.radiograph.image,
                                          "contours": {lb: p for lb, p in found.as_dict().items()}}
                row["frames"].append(entry)
            if found is not None:
                d = frame.radiograph.distortion
                views.append(found.observation(f"view{k + 1}", frame.radiograph.camera,
                                               d.undistort, d.distort))
        if refusal is not None:
            row["levels"][level] = {"status": "refused", "reason": refusal}
            continue
        try:
            outcome = solve_joint(plan, views, case.initial, config)
        except Exception as exc:  # a defect: recorded with its place
            where = traceback.extract_tb(exc.__traceback__)[-1]
            row["levels"][level] = {"status": "error",
                                    "reason": f"{type(exc).__name__}: {exc} ({where.filename}:{where.lineno})"}
            continue
        if outcome.status != "measured":
            row["levels"][level] = {"status": "refused", "reason": outcome.reason}
            continue
        ctr = abs(float(np.degrees(outcome.plane.ctr)) - case.truth_ctr_deg)
        str_ = abs(float(np.degrees(outcome.plane.str_)) - case.truth_str_deg)
        ok = ctr <= SUCCESS_DEG and str_ <= SUCCESS_DEG
        row["levels"][level] = {"status": "success" if ok else "wrong", "ctr_abs_deg": ctr, "str_abs_deg": str_}
    return row


_Extracted = tuple[ExtractedContours | None, str | None, float]


def _extracted(frame: RoomFrame, shadows: PinShadows, polarity: str = "auto") -> _Extracted:
    """One frame's contours at the pins' expected shadows (None and why where there are
    none), and the seconds their extraction took."""
    start = time.perf_counter()
    try:
        found = extract_contours(frame.radiograph.image, ContourConfig(polarity=polarity),
                                 expected_pins=shadows.centres, expected_pin_width_px=shadows.width_px,
                                 expected_pin_length_px=shadows.length_px)
    except ContourError as exc:
        return None, str(exc), time.perf_counter() - start
    return found, None, time.perf_counter() - start


def _again_as(polarity: str, frame: RoomFrame, shadows: PinShadows, first: _Extracted) -> _Extracted:
    """``first`` extracted again with ``polarity`` where it read the frame otherwise or
    could not extract it; the seconds are both extractions'."""
    if first[0] is not None and first[0].diagnostics["polarity"] == polarity:
        return first
    found, error, seconds = _extracted(frame, shadows, polarity)
    return found, error, first[2] + seconds


def _generic(reason: str) -> str:
    """A refusal's reason without its figures, to count alike reasons together."""
    return re.sub(r"[-+]?\d+(\.\d+)?", "#", reason)[:120]


def _summarise(rows: list[dict], levels: tuple[int, ...]) -> list[dict]:
    out = []
    for key in dict.fromkeys((r["model"], r["scene"]) for r in rows):
        group = [r for r in rows if (r["model"], r["scene"]) == key]
        frames = [f for r in group for f in r["frames"]]
        scored = [f for f in frames if not f["refused"]]
        distances = np.concatenate([np.asarray(f["distances"]) for f in scored]) if scored else np.zeros(0)
        coverage = [f["coverage"] for f in scored if np.isfinite(f["coverage"])]
        entry = {"model": key[0], "scene": key[1], "cases": len(group),
                 "skipped": [r["skipped"] for r in group if "skipped" in r],
                 "frames": len(frames), "frames_refused": sum(f["refused"] for f in frames),
                 "median_px": float(np.median(distances)) if len(distances) else None,
                 "p95_px": float(np.percentile(distances, 95)) if len(distances) else None,
                 "coverage_median": float(np.median(coverage)) if coverage else None,
                 "pins_labelled_pct": 100.0 * float(np.mean([f["pins_labelled"] for f in scored])) if scored else None,
                 "extraction_median_s": float(np.median([f["seconds"] for f in frames])) if frames else None,
                 "levels": {}}
        for level in levels:
            results = [r["levels"][level] for r in group if level in r["levels"]]
            counts = Counter(x["status"] for x in results)
            measured = [x for x in results if x["status"] in ("success", "wrong")]
            entry["levels"][str(level)] = {
                "solved": len(results), "success": counts["success"], "wrong": counts["wrong"],
                "refused": counts["refused"], "errors": counts["error"],
                "success_pct": 100.0 * counts["success"] / max(len(results), 1),
                "median_ctr_abs_deg": float(np.median([x["ctr_abs_deg"] for x in measured])) if measured else None,
                "median_str_abs_deg": float(np.median([x["str_abs_deg"] for x in measured])) if measured else None,
                "wrong_cases": [{"seed": r["seed"], **r["levels"][level]} for r in group
                                if r["levels"].get(level, {}).get("status") == "wrong"],
                "refusal_reasons": dict(Counter(_generic(x["reason"]) for x in results
                                                if x["status"] in ("refused", "error")).most_common()),
            }
        out.append(entry)
    return out


def _fmt(x, spec: str = ".2f") -> str:
    return "n/a" if x is None else format(x, spec)


def _table(summary: list[dict], levels: tuple[int, ...]) -> str:
    head = ("| model | scene | cases | frames refused | bone median px | p95 px | coverage | pins labelled "
            "| s/frame | " + " | ".join(f"L{lv} success / wrong / refused" for lv in levels) + " |")
    lines = [head, "|" + "---|" * (9 + len(levels))]
    for e in summary:
        cells = [f"{e['levels'][str(lv)]['success']}/{e['levels'][str(lv)]['solved']} "
                 f"({e['levels'][str(lv)]['success_pct']:.0f}%) / {e['levels'][str(lv)]['wrong']} / "
                 f"{e['levels'][str(lv)]['refused'] + e['levels'][str(lv)]['errors']}" for lv in levels]
        cov = None if e["coverage_median"] is None else 100 * e["coverage_median"]
        lines.append(f"| {e['model']} | {e['scene']} | {e['cases']} | {e['frames_refused']}/{e['frames']} "
                     f"| {_fmt(e['median_px'])} | {_fmt(e['p95_px'])} | {_fmt(cov, '.0f')}% "
                     f"| {_fmt(e['pins_labelled_pct'], '.0f')}% | {_fmt(e['extraction_median_s'])} | "
                     + " | ".join(cells) + " |")
    reasons = ["", "Refusal reasons (figures left out), per model and scene, first level:"]
    for e in summary:
        r = e["levels"][str(levels[0])]["refusal_reasons"]
        if r:
            reasons.append(f"- {e['model']} / {e['scene']}: " + "; ".join(f"{n}x {t}" for t, n in r.items()))
    return "\n".join(lines + reasons)


def _montage(rows: list[dict], path: Path) -> None:
    tiles = []
    for row in rows:
        if "montage" not in row or any(t[0] == (row["model"], row["scene"]) for t in tiles):
            continue
        image = row["montage"]["image"].astype(np.float64)
        lo, hi = np.percentile(image, [0.5, 99.5])
        grey = (np.clip((image - lo) / max(hi - lo, 1e-9), 0, 1) * 255).astype(np.uint8)
        colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
        for label, bgr in (("bone", (0, 200, 0)), ("pin1", (0, 0, 255)), ("pin2", (255, 0, 0))):
            for u, v in np.round(row["montage"]["contours"][label]).astype(int):
                cv2.circle(colour, (int(u), int(v)), 2, bgr, -1)
        tile = cv2.resize(colour, (320, 320), interpolation=cv2.INTER_AREA)
        cv2.putText(tile, f"{row['model']}: {row['scene']}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (0, 255, 255), 1)
        tiles.append(((row["model"], row["scene"]), tile))
    if not tiles:
        return
    columns = 4
    blank = np.zeros_like(tiles[0][1])
    images = [t for _, t in tiles] + [blank] * (-len(tiles) % columns)
    grid = np.vstack([np.hstack(images[i:i + columns]) for i in range(0, len(images), columns)])
    cv2.imwrite(str(path), grid)


def run_realism(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    models = [m for m in args.models if m == "phantom" or (args.data / "knee-smith2019" / "tibia-right.stl").is_file()]
    jobs = [(model, scene, args.seed + i, tuple(args.levels), str(args.data))
            for model in models for scene in args.scenes for i in range(args.cases)]
    start = time.perf_counter()
    if args.workers > 1:
        with ProcessPoolExecutor(args.workers) as pool:
            rows = list(pool.map(realism_case, jobs))
    else:
        rows = [realism_case(job) for job in jobs]
    summary = _summarise(rows, tuple(args.levels))
    _montage(rows, args.out / "montage.png")
    for r in rows:
        r.pop("montage", None)
    protocol = {"cases": args.cases, "levels": args.levels, "scenes": args.scenes, "models": models,
                "seed": args.seed, "seconds": time.perf_counter() - start}
    (args.out / "results.json").write_text(json.dumps({"protocol": protocol, "summary": summary,
                                                       "cases": rows}, indent=1))
    table = _table(summary, tuple(args.levels))
    (args.out / "results.md").write_text(f"# Realism study\n\n{json.dumps(protocol)}\n\n{table}\n")
    print(table)
    return 1 if any(lv["errors"] for e in summary for lv in e["levels"].values()) else 0


def _scenes(text: str) -> list[str]:
    """Comma-separated scenes, in the order given; a scene of several nuisances joins them
    with ``+``."""
    known = ("idealised", "operating-room") + NUISANCES
    if text == "all":
        return names_from(text, known, "scene")
    scenes = [n.strip() for n in text.split(",") if n.strip()]
    for scene in scenes or [""]:
        if "+" in scene:
            names_from(scene.replace("+", ","), NUISANCES, "nuisance")
        else:
            names_from(scene, known, "scene")
    return scenes


def add_realism_bench_parser(kinds: argparse._SubParsersAction) -> None:
    p = kinds.add_parser("realism", help="operating-room frames: each nuisance alone and all at once")
    p.add_argument("--cases", type=int, default=30, help="cases per scene and model (two frames each)")
    p.add_argument("--levels", type=lambda s: [int(x) for x in s.split(",")], default=[1, 3])
    p.add_argument("--scenes", type=_scenes, default=_scenes("all"),
                   help="comma-separated scenes, or 'all': idealised, operating-room, " + ", ".join(NUISANCES)
                   + "; nuisances joined by + make one scene (femur+retractors)")
    p.add_argument("--models", type=lambda s: [m.strip() for m in s.split(",")], default=["phantom", "real"],
                   help="phantom and/or real (the shared real tibia, when present)")
    p.add_argument("--data", type=Path, default=SHARED_DATA,
                   help="folder holding knee-nuisance/ and knee-smith2019/")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.set_defaults(func=run_realism)
