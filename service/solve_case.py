"""``slamtka solve``: measure the resection plane of a case folder and print the result."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from slamtka.solver.case import load_case
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.plan import Target
from slamtka.solver.result import Angles, Deviation, measured_angles, result_document
from slamtka.solver.slam import METHODS, SolveOutcome, SolverConfig, solve_joint

__all__ = ["add_solve_parser", "cmd_solve"]


def _summary(case_id: str, outcome: SolveOutcome, target: Target,
             measured: tuple[Angles, Deviation] | None, method: str) -> str:
    lines = [f"case {case_id}: {outcome.status.replace('_', ' ')}"]
    if measured is None:
        lines.append(f"  reason: {outcome.reason or None}")
    else:
        (a, d), t = measured, target
        lines += [
            f"  CTR {a.ctr_deg:+6.2f} deg +- {a.ctr_sigma_deg:.2f}  (plan {t.ctr_deg:+.1f}, "
            f"deviation {d.ctr_deg:+.2f})   positive = varus",
            f"  STR {a.str_deg:+6.2f} deg +- {a.str_sigma_deg:.2f}  (plan {t.str_deg:+.1f}, "
            f"deviation {d.str_deg:+.2f})   positive = posterior slope",
            f"  within +-{t.tolerance_deg:.1f} deg of plan: {'yes' if d.within_tolerance else 'NO'}",
        ]
    rms = ", ".join(f"{k} {v:.2f}" for k, v in outcome.residual_rms.items())
    lines.append(f"  solver ({method}, started from the {outcome.initialisation}): "
                 f"{outcome.iterations} iterations, {outcome.seconds:.2f} s, "
                 f"{outcome.convergence_reason}; residual RMS (sigmas): {rms or 'n/a'}")
    return "\n".join(lines)


def _truth_line(folder: Path, angles: Angles | None) -> str | None:
    path = folder / "ground_truth.json"
    if not path.is_file() or angles is None:
        return None
    truth = read_json_object(path)
    e_ctr = angles.ctr_deg - truth["ctr_deg"]
    e_str = angles.str_deg - truth["str_deg"]
    return (f"  simulated truth: CTR {truth['ctr_deg']:+.2f}, STR {truth['str_deg']:+.2f} deg; "
            f"error CTR {e_ctr:+.3f}, STR {e_str:+.3f} deg")


def cmd_solve(args: argparse.Namespace) -> int:
    case = load_case(args.case_dir)
    outcome = solve_joint(case.plan, case.views, case.initial, SolverConfig(method=args.method))
    doc = result_document(case.case_id, outcome, case.plan, case.views, case.calibration_id,
                          args.method)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2))
    measured = measured_angles(outcome, case.plan)
    print(_summary(case.case_id, outcome, case.plan.target, measured, args.method))
    truth = _truth_line(args.case_dir, None if measured is None else measured[0])
    if truth:
        print(truth)
    return 0 if outcome.status == "measured" else 3


def add_solve_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("solve", help="measure the resection plane of a case folder")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--json", type=Path, help="write the result document here")
    p.add_argument("--method", choices=METHODS, default="slam",
                   help="the proposed method (default) or one of the paper's baselines")
    p.set_defaults(func=cmd_solve)
