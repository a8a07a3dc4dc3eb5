"""``slamtka bench degenerate``: the honest-failure study (see :mod:`solver.degenerate`).

For every kind of spoiled case, ``--cases`` freshly simulated ones are solved in worker
processes; each answer is a refusal (with its reason), a correct angle (both CTR and STR
within ``--tolerance`` of the truth) or a wrong angle. The target for wrong angles is zero.
Prints the table and writes ``degenerate.json`` with every case.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.degenerate import DEGENERATE_KINDS, degenerate_case
from slamtka.solver.plan import Plan
from slamtka.solver.slam import solve_joint

__all__ = ["add_degenerate_bench_parser"]

_plans: dict[str, Plan] = {}


def _init_worker() -> None:
    for side in ("left", "right"):
        _plans[side] = phantom_plan(side)
        _plans[side].bone_model()
        _plans[side].pin_model()


def _run_one(job: tuple[str, int, float]) -> dict:
    kind, seed, tolerance_deg = job
    spoiled = degenerate_case(_plans, kind, seed)
    outcome = solve_joint(spoiled.plan, spoiled.views, spoiled.case.initial)
    row = {"kind": kind, "seed": seed, "status": outcome.status, "reason": outcome.reason,
           "ctr_error_deg": None, "str_error_deg": None}
    if outcome.status == "measured":
        row["ctr_error_deg"] = float(np.degrees(outcome.plane.ctr)) - spoiled.case.truth_ctr_deg
        row["str_error_deg"] = float(np.degrees(outcome.plane.str_)) - spoiled.case.truth_str_deg
        correct = max(abs(row["ctr_error_deg"]), abs(row["str_error_deg"])) <= tolerance_deg
        row["verdict"] = "correct" if correct else "wrong angle"
    else:
        row["verdict"] = "refused"
    return row


def _reason_family(reason: str) -> str:
    """A refusal reason without its numbers, for counting."""
    return reason.split(" (")[0]


def run_degenerate(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(kind, args.seed + i, args.tolerance) for kind in args.kinds for i in range(args.cases)]
    with ProcessPoolExecutor(args.workers, initializer=_init_worker) as pool:
        rows = list(pool.map(_run_one, jobs))
    summary = []
    lines = ["| kind | cases | refused | measured correctly | wrong angles | main refusal reasons |",
             "|---|---|---|---|---|---|"]
    for kind in args.kinds:
        mine = [r for r in rows if r["kind"] == kind]
        verdicts = Counter(r["verdict"] for r in mine)
        reasons = Counter(_reason_family(r["reason"]) for r in mine if r["verdict"] == "refused")
        summary.append({"kind": kind, "cases": len(mine), **{v: verdicts.get(v, 0) for v in
                        ("refused", "correct", "wrong angle")}, "reasons": dict(reasons)})
        top = "; ".join(f"{reason} ({n})" for reason, n in reasons.most_common(2))
        lines.append(f"| {kind} | {len(mine)} | {verdicts['refused']} | {verdicts['correct']} "
                     f"| {verdicts['wrong angle']} | {top} |")
    wrong = sum(s["wrong angle"] for s in summary)
    lines.append(f"\n{len(rows)} cases, {wrong} wrong angles returned (tolerance "
                 f"{args.tolerance:g} deg)")
    (args.out / "degenerate.json").write_text(json.dumps(
        {"tolerance_deg": args.tolerance, "summary": summary, "wrong_angles": wrong,
         "cases": rows}, indent=2))
    print("\n".join(lines))
    return 0


def _kinds(text: str) -> list[str]:
    kinds = list(DEGENERATE_KINDS) if text == "all" else [k.strip() for k in text.split(",")]
    unknown = [k for k in kinds if k not in DEGENERATE_KINDS]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown kind(s) {unknown}; choose from "
                                         f"{', '.join(DEGENERATE_KINDS)}")
    return kinds


def add_degenerate_bench_parser(kinds: argparse._SubParsersAction) -> None:
    p = kinds.add_parser("degenerate", help="spoiled cases: refusals, correct and wrong angles")
    p.add_argument("--cases", type=int, default=200, help="cases per kind")
    p.add_argument("--kinds", type=_kinds, default=list(DEGENERATE_KINDS),
                   help=f"comma-separated, or 'all': {', '.join(DEGENERATE_KINDS)}")
    p.add_argument("--tolerance", type=float, default=1.0, help="degrees, on CTR and STR")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    p.set_defaults(func=run_degenerate)
