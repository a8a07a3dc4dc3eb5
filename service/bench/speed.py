"""``slamtka bench speed``: where a solve spends its time, and how much memory it takes.

Solves freshly simulated cases one after another in this process (the plan's models built
beforehand, as the service does when it loads a plan), and reports per solve the total
time, the iterations, the time per iteration and each stage's share (from the solver's
per-iteration callback), then the peak memory one solve allocates (``tracemalloc``, which
numpy reports to; measured in a separate pass so that tracing does not slow the timed one)
and the process's peak resident size. Prints a table and writes ``speed.json``.

Wall-clock time is the figure that matters at the table side, but on a shared virtual
machine it also measures the neighbours; the process CPU time of each solve (all its
threads) is reported beside it as the steadier measure of the solver's own cost.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
import tracemalloc
from pathlib import Path

import numpy as np

from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.simulate import SimulationConfig, simulate_case
from slamtka.solver.plan import Plan
from slamtka.solver.slam import SolverConfig, solve_joint


def _timed_solve(plan: Plan, seed: int, level: int) -> dict:
    case = simulate_case(plan, SimulationConfig.at_level(level, seed))
    marks: list[tuple[str, float]] = []
    start, cpu_start = time.perf_counter(), time.process_time()
    outcome = solve_joint(plan, case.views, case.initial, SolverConfig(),
                          lambda stage, info: marks.append((stage, time.perf_counter())))
    total, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    stages: dict[str, dict] = {}
    previous = start
    for stage, at in marks:
        entry = stages.setdefault(stage, {"iterations": 0, "seconds": 0.0})
        entry["iterations"] += 1
        entry["seconds"] += at - previous
        previous = at
    return {"seed": seed, "status": outcome.status, "seconds": total, "cpu_seconds": cpu,
            "iterations": outcome.iterations, "seconds_per_iteration": total / max(outcome.iterations, 1),
            "after_last_iteration_s": total - (previous - start), "stages": stages}


def _peak_allocation_mb(plan: Plan, seed: int, level: int) -> float:
    tracemalloc.start()
    try:
        _timed_solve(plan, seed, level)
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def _table(runs: list[dict], peak_mb: float, rss_mb: float) -> str:
    totals = np.array([r["seconds"] for r in runs])
    cpu = np.array([r["cpu_seconds"] for r in runs])
    iterations = np.array([r["iterations"] for r in runs])
    per_iteration = np.array([r["seconds_per_iteration"] for r in runs])
    lines = [f"{len(runs)} solves: total median {np.median(totals):.2f} s (p95 "
             f"{np.percentile(totals, 95):.2f}, max {totals.max():.2f}); iterations median "
             f"{np.median(iterations):.0f}; time per iteration median {1000 * np.median(per_iteration):.1f} ms",
             f"CPU time per solve median {np.median(cpu):.2f} s (p95 {np.percentile(cpu, 95):.2f})",
             f"peak memory allocated by one solve {peak_mb:.0f} MB; process peak resident {rss_mb:.0f} MB",
             "", "| stage | median iterations | median seconds |", "|---|---|---|"]
    names = list(dict.fromkeys(name for r in runs for name in r["stages"]))
    for name in names:
        its = [r["stages"].get(name, {}).get("iterations", 0) for r in runs]
        secs = [r["stages"].get(name, {}).get("seconds", 0.0) for r in runs]
        lines.append(f"| {name} | {np.median(its):.0f} | {np.median(secs):.3f} |")
    lines.append(f"| (gates, plane, covariance) | - | "
                 f"{np.median([r['after_last_iteration_s'] for r in runs]):.3f} |")
    return "\n".join(lines)


def warmed_plan(args: argparse.Namespace) -> Plan:
    """The plan of ``--tibia``, ``--fibula``, ``--landmarks`` (the phantom without), its
    models built, as the service has them once started."""
    plan = phantom_plan() if args.tibia is None else Plan.from_meshes(args.tibia, args.fibula,
                                                                      args.landmarks)
    plan.bone_model()
    plan.pin_model()
    return plan


def run_speed(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    plan = warmed_plan(args)
    runs = [_timed_solve(plan, args.seed + i, args.level) for i in range(args.cases)]
    peak_mb = _peak_allocation_mb(plan, args.seed, args.level)
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    doc = {"cases": args.cases, "level": args.level,
           "model": "phantom" if args.tibia is None else str(args.tibia),
           "median_seconds": float(np.median([r["seconds"] for r in runs])),
           "median_cpu_seconds": float(np.median([r["cpu_seconds"] for r in runs])),
           "median_iterations": float(np.median([r["iterations"] for r in runs])),
           "median_seconds_per_iteration": float(np.median([r["seconds_per_iteration"] for r in runs])),
           "peak_allocated_mb_per_solve": peak_mb, "process_peak_rss_mb": rss_mb, "runs": runs}
    (args.out / "speed.json").write_text(json.dumps(doc, indent=2))
    print(_table(runs, peak_mb, rss_mb))
    return 0


def add_speed_bench_parser(kinds: argparse._SubParsersAction) -> None:
    p = kinds.add_parser("speed", help="time per solve, per iteration and per stage; memory")
    p.add_argument("--cases", type=int, default=10)
    p.add_argument("--level", type=int, default=1, help="initial-noise level of the cases")
    p.add_argument("--tibia", type=Path)
    p.add_argument("--fibula", type=Path)
    p.add_argument("--landmarks", type=Path)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.set_defaults(func=run_speed)
