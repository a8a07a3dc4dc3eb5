"""``slamtka bench search``: what the global set-up searches cost, and what they find.

The searches (:mod:`slamtka.solver.setup_search`) run only when the solve from the
encoders' guess goes astray, which the far-off cases of level 3 and above do. For each
simulated case (the seeds of ``bench accuracy`` at that level) this times every configured
search on the case's initial poses, as the solver runs it, in process CPU time (all
threads) and wall time, counts its template correlations, measures the set-up error it
leaves (rotation and translation at the knee, against the simulated truth) and runs the
solve from its result. A case *needs* the first search when the solve from the encoders
goes astray, the second when the solve after the first does too. Writes ``search.json``
(with each search's correction, to compare the poses two versions choose) and prints a
table.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slamtka.bench.speed import warmed_plan
from slamtka.sim.simulate import SimulatedCase, SimulationConfig, simulate_case
from slamtka.solver.geometry import Pose, so3_log
from slamtka.solver.plan import Plan
from slamtka.solver.problem import InitialGuess
from slamtka.solver.setup_search import search_setup
from slamtka.solver.slam import SolveOutcome, SolverConfig, solve_joint


@contextmanager
def _counted_correlations() -> Iterator[list[int]]:
    """Counts OpenCV's template correlations while the block runs (one list item)."""
    original: Any = cv2.matchTemplate
    count = [0]

    def counting(*args: Any, **kwargs: Any) -> Any:
        count[0] += 1
        return original(*args, **kwargs)

    cv2.matchTemplate = counting
    try:
        yield count
    finally:
        cv2.matchTemplate = original


def _set_up_error(plan: Plan, case: SimulatedCase, T_cam_tibia: Pose) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) between the first view's pose and the truth,
    at the knee (anatomical frame)."""
    anatomy = plan.landmarks.T_tibia_anat()
    D = (case.truth_T_cam_tibia[0] @ anatomy).inverse() @ (T_cam_tibia @ anatomy)
    return float(np.degrees(np.linalg.norm(so3_log(D.R)))), float(np.linalg.norm(D.t))


def _solved(plan: Plan, case: SimulatedCase, T_cam_tibia: list[Pose]) -> SolveOutcome:
    """One solve from ``T_cam_tibia`` without the searches (what the solver runs after one)."""
    initial = InitialGuess(tuple(T_cam_tibia), case.initial.T_tibia_pin,
                           case.initial.odometry_sigma)
    return solve_joint(plan, case.views, initial, SolverConfig(global_searches=()))


def _solve_row(plan: Plan, case: SimulatedCase, T_cam_tibia: list[Pose]) -> dict:
    start = time.process_time()
    outcome = _solved(plan, case, T_cam_tibia)
    row = {"status": outcome.status, "went_astray": outcome.went_astray,
           "cpu_s": time.process_time() - start, "angle_errors_deg": None}
    if outcome.angles_deg is not None:
        ctr, str_ = outcome.angles_deg
        row["angle_errors_deg"] = [abs(ctr - case.truth_ctr_deg), abs(str_ - case.truth_str_deg)]
    return row


def _one_case(plan: Plan, seed: int, level: int, searches: int) -> dict:
    case = simulate_case(plan, SimulationConfig.at_level(level, seed))
    initial = list(case.initial.T_cam_tibia)
    first = _solve_row(plan, case, initial)
    observed = [(T, v.camera, v.distance_map("bone"), v.contours["bone"])
                for T, v in zip(initial, case.views)]
    anatomy = plan.landmarks.T_tibia_anat()
    rows, needed = [], first["went_astray"]
    for search in SolverConfig().global_searches[:searches]:
        with _counted_correlations() as count:
            start, cpu = time.perf_counter(), time.process_time()
            C = search_setup(plan.bone_model().coarse_contour, observed, anatomy, search)
            wall, cpu = time.perf_counter() - start, time.process_time() - cpu
        poses = [T @ C for T in initial]
        after = _solve_row(plan, case, poses)
        rows.append({"needed": needed, "cpu_s": cpu, "wall_s": wall, "correlations": count[0],
                     "left_deg_mm": _set_up_error(plan, case, poses[0]),
                     "correction": {"rotvec": so3_log(C.R).tolist(), "t": C.t.tolist()},
                     "solve_after": after})
        needed = needed and after["went_astray"]
    return {"seed": seed, "initial_error_deg_mm": _set_up_error(plan, case, initial[0]),
            "first_solve": first, "searches": rows}


def _table(cases: list[dict]) -> str:
    lines = ["| seed | initial error (deg, mm) | first solve | search | needed | CPU s | wall s "
             "| correlations | error left (deg, mm) | solve after (CPU s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        for k, s in enumerate(c["searches"], 1):
            after = s["solve_after"]
            lines.append(
                f"| {c['seed']} | {c['initial_error_deg_mm'][0]:.0f}, {c['initial_error_deg_mm'][1]:.0f} "
                f"| {'astray' if c['first_solve']['went_astray'] else c['first_solve']['status']} "
                f"| {k} | {'yes' if s['needed'] else 'no'} | {s['cpu_s']:.2f} | {s['wall_s']:.2f} "
                f"| {s['correlations']} | {s['left_deg_mm'][0]:.1f}, {s['left_deg_mm'][1]:.1f} "
                f"| {'astray' if after['went_astray'] else after['status']} ({after['cpu_s']:.2f}) |")
    lines.append("")
    for k in range(max(len(c["searches"]) for c in cases)):
        rows = [c["searches"][k] for c in cases]
        cpu = np.array([s["cpu_s"] for s in rows])
        lines.append(f"search {k + 1}: CPU median {np.median(cpu):.2f} s, max {cpu.max():.2f} s; "
                     f"{np.median([s['correlations'] for s in rows]):.0f} correlations; needed by "
                     f"{sum(s['needed'] for s in rows)} of {len(rows)} cases")
    return "\n".join(lines)


def run_search(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    plan = warmed_plan(args)
    cases = [_one_case(plan, args.seed + 1000 * args.level + i, args.level, args.searches)
             for i in range(args.cases)]
    (args.out / "search.json").write_text(json.dumps(
        {"level": args.level, "model": "phantom" if args.tibia is None else str(args.tibia),
         "cases": cases}, indent=2))
    print(_table(cases))
    return 0


def add_search_bench_parser(kinds: argparse._SubParsersAction) -> None:
    p = kinds.add_parser("search", help="the global set-up searches: time, correlations, result")
    p.add_argument("--cases", type=int, default=10)
    p.add_argument("--level", type=int, default=3, help="initial-noise level of the cases")
    p.add_argument("--searches", type=int, default=2, help="how many of the configured searches")
    p.add_argument("--tibia", type=Path)
    p.add_argument("--fibula", type=Path)
    p.add_argument("--landmarks", type=Path)
    p.add_argument("--seed", type=int, default=0, help="as bench accuracy's: cases seed + 1000 level + i")
    p.add_argument("--out", type=Path, required=True)
    p.set_defaults(func=run_search)
