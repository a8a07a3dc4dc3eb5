"""``slamtka bench accuracy``: the simulation study of docs/evaluation.md.

Each run simulates a fresh case (2 px contour noise by default, initial-state noise at the
chosen level: rotation SD 0.1 rad x level, translation SD 20 mm x level), solves it and
records the absolute CTR/STR errors against the simulated truth, the reported 1-sigma, the
time and the iterations. ``--segmentation-mm`` adds a smooth CT segmentation error to the
bone the X-rays see (the plan keeps its mesh), beyond the paper's protocol; the plan states
the same SD, which the solver carries as an error shared by nearby edge points. Runs are spread over worker processes. Writes ``results.json``,
``results.md`` (table) and ``errors.png`` (box plots) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from slamtka.bench.args import names_from
from slamtka.bench.degenerate import add_degenerate_bench_parser
from slamtka.bench.hardening import add_hardening_bench_parser
from slamtka.bench.imaging import add_imaging_bench_parser
from slamtka.bench.link import add_link_bench
from slamtka.bench.realism import add_realism_bench_parser
from slamtka.bench.search import add_search_bench_parser
from slamtka.bench.service import add_service_bench_parser
from slamtka.bench.speed import add_speed_bench_parser
from slamtka.bench.workflow import add_workflow_bench_parser
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.simulate import (
    ROT_SD_PER_LEVEL_RAD,
    TRANS_SD_PER_LEVEL_MM,
    SimulationConfig,
    SimulationError,
    simulate_case,
)
from slamtka.solver.pin_naming import swap_pins
from slamtka.solver.plan import Plan
from slamtka.solver.slam import METHODS, SolverConfig, solve_joint

SUCCESS_DEG = 1.0

_worker_plan: Plan | None = None


def _init_worker(tibia: Path | None, fibula: Path | None, landmarks: Path | None,
                 segmentation_mm: float) -> None:
    """The study's plan, which states the segmentation error the study simulates (none in
    the paper's protocol, where the mesh is the bone), as a plan from CT would."""
    global _worker_plan
    _worker_plan = phantom_plan() if tibia is None else Plan.from_meshes(tibia, fibula, landmarks)
    _worker_plan.segmentation_sd_mm = segmentation_mm
    _worker_plan.bone_model()
    _worker_plan.pin_model()


def _run_one(job: tuple[str, int, int, float, float, bool]) -> dict:
    method, level, seed, noise_px, segmentation_mm, swap_names = job
    plan = _worker_plan
    start = time.perf_counter()
    row = {"method": method, "level": level, "seed": seed,
           "ctr_abs_deg": None, "str_abs_deg": None, "ctr_sigma_deg": None, "str_sigma_deg": None,
           "odometry_rms_sigma": None, "initialisation": None, "both_namings": False}
    try:
        case = simulate_case(plan, replace(SimulationConfig.at_level(level, seed, noise_px),
                                           segmentation_sd_mm=segmentation_mm))
    except SimulationError as exc:  # the simulator's case, not the solver's: skip it, go on
        row.update(time_s=0.0, iterations=0, status="skipped", reason=f"seed {seed}: {exc}")
        return row
    try:
        # --swap-pin-names: extraction's guess wrong in the last view.
        views = case.views[:-1] + [swap_pins(case.views[-1])] if swap_names else case.views
        outcome = solve_joint(plan, views, case.initial, SolverConfig(method=method))
    except Exception as exc:  # a defect: recorded with its place, so one run cannot sink a study
        where = traceback.extract_tb(exc.__traceback__)[-1]
        row.update(time_s=time.perf_counter() - start, iterations=0, status="error",
                   reason=f"{type(exc).__name__}: {exc} ({where.filename}:{where.lineno})")
        return row
    row.update(time_s=time.perf_counter() - start, iterations=outcome.iterations,
               status=outcome.status, reason=outcome.reason,
               odometry_rms_sigma=outcome.residual_rms.get("E_odo"),
               initialisation=outcome.initialisation, both_namings=bool(outcome.unclear_naming))
    if outcome.status == "measured":
        sigma = np.degrees(np.sqrt(np.diag(outcome.angle_cov)))
        row.update(ctr_abs_deg=abs(float(np.degrees(outcome.plane.ctr)) - case.truth_ctr_deg),
                   str_abs_deg=abs(float(np.degrees(outcome.plane.str_)) - case.truth_str_deg),
                   ctr_sigma_deg=float(sigma[0]), str_sigma_deg=float(sigma[1]))
    return row


def _stats(values: list[float | None]) -> tuple[float, float]:
    v = np.array([x for x in values if x is not None], float)
    if v.size == 0:
        return float("nan"), float("nan")
    return float(np.median(v)), float(np.percentile(v, 95))


def _within(r: dict, keys: tuple[str, ...], k: float) -> float:
    """Share of measured angles of ``keys`` ("ctr", "str") whose error is within k sigma."""
    pairs = [(e, s) for key in keys
             for e, s in zip(r[f"{key}_abs_deg"], r[f"{key}_sigma_deg"]) if e is not None]
    return 100 * float(np.mean([e <= k * s for e, s in pairs])) if pairs else float("nan")


def _table(results: list[dict]) -> str:
    """Methods x levels. Success: both angles within 1 deg; wrong: measured, but an angle
    off by more; coverage of the reported 1-sigma and 2-sigma, CTR and STR pooled and apart."""
    lines = ["| method | level | rot SD (rad) | trans SD (mm) | runs | measured | median CTR | p95 CTR "
             "| median STR | p95 STR | success (<=1 deg) | wrong | within 1 sigma (CTR / STR) "
             "| within 2 sigma (CTR / STR) | median time (s) | both namings solved |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        mc, pc = _stats(r["ctr_abs_deg"])
        ms, ps = _stats(r["str_abs_deg"])
        measured = [(c, s) for c, s in zip(r["ctr_abs_deg"], r["str_abs_deg"]) if c is not None]
        success = sum(c <= SUCCESS_DEG and s <= SUCCESS_DEG for c, s in measured)
        coverage = ["{:.0f}% ({:.0f} / {:.0f})".format(_within(r, ("ctr", "str"), k),
                                                       _within(r, ("ctr",), k), _within(r, ("str",), k))
                    for k in (1, 2)]
        lines.append(
            f"| {r['method']} | {r['level']} | {r['rot_sd_rad']:.1f} | {r['trans_sd_mm']:.0f} "
            f"| {r['runs']} | {r['converged']} | {mc:.3f} | {pc:.3f} | {ms:.3f} | {ps:.3f} "
            f"| {100 * success / max(r['runs'], 1):.0f}% | {len(measured) - success} "
            f"| {coverage[0]} | {coverage[1]} | {np.median(r['time_s']):.2f} "
            f"| {r['solved_under_both_namings']} |")
    return "\n".join(lines)


def _plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, key, title in ((axes[0], "ctr_abs_deg", "|CTR error|"), (axes[1], "str_abs_deg", "|STR error|")):
        data = [[x for x in r[key] if x is not None] or [np.nan] for r in results]
        ax.boxplot(data, tick_labels=[f"{r['method']}\nL{r['level']}" for r in results])
        ax.set_title(title)
        ax.set_ylabel("degrees")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _summary(method: str, level: int, rows: list[dict]) -> dict:
    """One method at one level: per-run figures in the order of the seeds; cases the
    simulator could not build are listed apart (``skipped``, with their seeds)."""
    skipped = [r["reason"] for r in rows if r["status"] == "skipped"]
    rows = [r for r in rows if r["status"] != "skipped"]
    return {
        "method": method, "level": level,
        "rot_sd_rad": ROT_SD_PER_LEVEL_RAD * level, "trans_sd_mm": TRANS_SD_PER_LEVEL_MM * level,
        "runs": len(rows), "converged": sum(r["status"] == "measured" for r in rows),
        **{key: [r[key] for r in rows] for key in
           ("ctr_abs_deg", "str_abs_deg", "ctr_sigma_deg", "str_sigma_deg", "time_s", "iterations",
            "odometry_rms_sigma", "initialisation")},
        "solved_under_both_namings": sum(r["both_namings"] for r in rows),
        "refusals": [r["reason"] for r in rows if r["status"] != "measured"],
        "skipped": skipped,
    }


def run_accuracy(args: argparse.Namespace) -> int:
    _check_model(args)
    args.out.mkdir(parents=True, exist_ok=True)
    # Every method sees the same simulated cases (same seeds) at each level.
    jobs = [(method, level, args.seed + 1000 * level + run, args.noise_px, args.segmentation_mm,
             args.swap_pin_names)
            for method in args.methods for level in args.levels for run in range(args.runs)]
    with ProcessPoolExecutor(args.workers, initializer=_init_worker,
                             initargs=(args.tibia, args.fibula, args.landmarks,
                                       args.segmentation_mm)) as pool:
        rows = list(pool.map(_run_one, jobs))
    results = [_summary(method, level, [r for r in rows if r["level"] == level and r["method"] == method])
               for method in args.methods for level in args.levels]
    protocol = {"methods": list(args.methods), "noise_px": args.noise_px,
                "segmentation_sd_mm": args.segmentation_mm, "pin_names_swapped": args.swap_pin_names,
                "runs_per_level": args.runs, "levels": list(args.levels),
                "rot_sd_per_level_rad": ROT_SD_PER_LEVEL_RAD,
                "trans_sd_per_level_mm": TRANS_SD_PER_LEVEL_MM,
                "model": "phantom" if args.tibia is None else str(args.tibia), "seed": args.seed}
    (args.out / "results.json").write_text(json.dumps({"protocol": protocol, "results": results},
                                                      indent=2))
    table = _table(results)
    (args.out / "results.md").write_text(f"# Accuracy study\n\n{json.dumps(protocol)}\n\n{table}\n")
    _plot(results, args.out / "errors.png")
    print(table)
    for r in rows:
        if r["status"] == "skipped":
            print(f"skipped {r['method']} level {r['level']}: {r['reason']}")
    errors = [r for r in rows if r["status"] == "error"]
    for r in errors:
        print(f"ERROR {r['method']} level {r['level']} seed {r['seed']}: {r['reason']}")
    return 1 if errors else 0


def _check_model(args: argparse.Namespace) -> None:
    """Refuse, naming the option or file, a model the workers could not build: their
    initialiser's error would only end the pool ("a process ... terminated abruptly")."""
    if args.tibia is None:
        if args.fibula is not None or args.landmarks is not None:
            raise ValueError("--fibula and --landmarks describe a --tibia mesh; give it too")
        return
    if args.landmarks is None:
        raise ValueError(f"--tibia {args.tibia} needs --landmarks: the tibia's landmarks JSON "
                         "(its knee and ankle centres, as tests/data/knee-smith2019-landmarks.json)")
    Plan.from_meshes(args.tibia, args.fibula, args.landmarks)


def _methods(text: str) -> list[str]:
    return names_from(text, METHODS, "method")


def add_bench_parser(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmarks that print figures")
    kinds = bench.add_subparsers(dest="bench", required=True)
    p = kinds.add_parser("accuracy", help="the simulation study of docs/evaluation.md")
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--levels", type=lambda s: [int(x) for x in s.split(",")], default=[1, 2, 3, 4, 5])
    p.add_argument("--methods", type=_methods, default=["slam"],
                   help=f"comma-separated, or 'all': {', '.join(METHODS)}")
    p.add_argument("--noise-px", type=float, default=2.0)
    p.add_argument("--segmentation-mm", type=float, default=0.0,
                   help="SD of a smooth CT segmentation error of the bone (0: the paper's protocol)")
    p.add_argument("--tibia", type=Path)
    p.add_argument("--fibula", type=Path)
    p.add_argument("--landmarks", type=Path)
    p.add_argument("--swap-pin-names", action="store_true",
                   help="swap the two pins' names in the last view of every case (a wrong guess "
                        "of extraction), to measure how the solver names them")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.set_defaults(func=run_accuracy)
    add_link_bench(kinds)
    add_service_bench_parser(kinds)
    add_speed_bench_parser(kinds)
    add_search_bench_parser(kinds)
    add_workflow_bench_parser(kinds)
    add_degenerate_bench_parser(kinds)
    add_imaging_bench_parser(kinds)
    add_realism_bench_parser(kinds)
    add_hardening_bench_parser(kinds)
