"""``slamtka solve``: measure the resection plane of a case folder and print the result."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from slamtka.solver.case import load_case
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.result import result_document
from slamtka.solver.slam import METHODS, SolverConfig, solve_joint

__all__ = ["add_solve_parser", "cmd_solve"]


def _summary(doc: dict) -> str:
    lines = [f"case {doc['case_id']}: {doc['status'].replace('_', ' ')}"]
    if doc["angles"] is None:
        lines.append(f"  reason: {doc['reason']}")
    else:
        a, d, t = doc["angles"], doc["deviation"], doc["target"]
        lines += [
            f"  CTR {a['ctr_deg']:+6.2f} deg +- {a['ctr_sigma_deg']:.2f}  (plan {t['ctr_deg']:+.1f}, "
            f"deviation {d['ctr_deg']:+.2f})   positive = varus",
            f"  STR {a['str_deg']:+6.2f} deg +- {a['str_sigma_deg']:.2f}  (plan {t['str_deg']:+.1f}, "
            f"deviation {d['str_deg']:+.2f})   positive = posterior slope",
            f"  within +-{t['tolerance_deg']:.1f} deg of plan: {'yes' if d['within_tolerance'] else 'NO'}",
        ]
    s = doc["solver"]
    rms = ", ".join(f"{k} {v:.2f}" for k, v in s["residual_rms_sigma"].items())
    lines.append(f"  solver ({s['method']}, started from the {s['start']}): {s['iterations']} "
                 f"iterations, {s['seconds']:.2f} s, {s['convergence_reason']}; residual RMS "
                 f"(sigmas): {rms or 'n/a'}")
    return "\n".join(lines)


def _truth_line(folder: Path, doc: dict) -> str | None:
    path = folder / "ground_truth.json"
    if not path.is_file() or doc["angles"] is None:
        return None
    truth = read_json_object(path)
    e_ctr = doc["angles"]["ctr_deg"] - truth["ctr_deg"]
    e_str = doc["angles"]["str_deg"] - truth["str_deg"]
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
    print(_summary(doc))
    truth = _truth_line(args.case_dir, doc)
    if truth:
        print(truth)
    return 0 if doc["status"] == "measured" else 3


def add_solve_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("solve", help="measure the resection plane of a case folder")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--json", type=Path, help="write the result document here")
    p.add_argument("--method", choices=METHODS, default="slam",
                   help="the proposed method (default) or one of the paper's baselines")
    p.set_defaults(func=cmd_solve)
