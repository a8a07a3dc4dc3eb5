"""``slamtka case list|show|rerun|new-set``: the cases of a service, from its data folder.

``list`` and ``show`` read what the service keeps on disk (pin sets, numbered runs and their
``result.json``) and work whether or not it runs. ``rerun`` (measure the current pin set
again without new X-rays, e.g. after a forgotten plan was added or a calibration corrected)
and ``new-set`` (the next view starts a new pin set) leave a request that the running service
takes within a second, or at its next start.
"""

from __future__ import annotations

import argparse
import getpass
import json
from pathlib import Path

from slamtka.service.config import load_config
from slamtka.service.pinsets import CasePinSets, PinSetStore
from slamtka.service.results import MeasurementResult
from slamtka.service.workflow import write_request

__all__ = ["add_case_parser"]


def _cases(data_dir: Path) -> list[CasePinSets]:
    folder = data_dir / "pinsets"
    return [PinSetStore.load(folder, p.stem) for p in sorted(folder.glob("case-*.json"))]


def _find(data_dir: Path, case_id: str) -> CasePinSets:
    matches = [c for c in _cases(data_dir) if c.case_id.startswith(case_id)]
    if len(matches) != 1:
        known = ", ".join(c.case_id for c in _cases(data_dir)) or "none"
        raise ValueError(f"{'no' if not matches else 'more than one'} case matches {case_id!r} "
                         f"(known: {known})")
    return matches[0]


def _angles(run: dict) -> str:
    if run.get("verdict") is None:
        return "running or interrupted"
    if run.get("ctr_deg") is None:
        return "not measured"
    return f"CTR {run['ctr_deg']:+.1f}, STR {run['str_deg']:+.1f} deg, {run['verdict']}"


def cmd_list(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    cases = _cases(config.data_dir)
    if not cases:
        print("no cases")
    for c in cases:
        runs = [r for s in c.sets for r in s.runs]
        last = (f"last: pin set {runs[-1]['pin_set']} #{runs[-1]['number']}: {_angles(runs[-1])}"
                if runs else "no run yet")
        views = sum(len(s.views) for s in c.sets)
        print(f"{c.case_id}  patient {c.describe.get('patient_id')} side "
              f"{c.describe.get('laterality') or '?'}  {len(c.sets)} pin set(s), {views} view(s)"
              f"{f', {len(c.left_out)} left out' if c.left_out else ''}  {last}")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    c = _find(config.data_dir, args.case)
    print(f"{c.case_id}: patient {c.describe.get('patient_id')}, side "
          f"{c.describe.get('laterality') or '?'}, study {c.describe.get('study_instance_uid')}")
    for s in c.sets:
        print(f"  pin set {s.number} (started by {s.started_by}): {len(s.views)} view(s)")
        for uid in s.views:
            print(f"    view {uid}")
        for run in s.runs:
            path = config.output / c.case_id / run["run_id"] / "result.json"
            reason = ""
            if path.is_file():
                result = MeasurementResult.from_document(json.loads(path.read_text()))
                reason = f" ({result.reason})" if result.reason else ""
            print(f"    measurement {run['number']} (run {run['run_id']}, {run['triggered']}): "
                  f"{_angles(run)}{reason}")
    for uid, why in c.left_out.items():
        print(f"  left out: view {uid}: {why}")
    if c.new_set_requested:
        print(f"  the next view starts a new pin set ({c.new_set_requested})")
    return 0


def cmd_request(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    c = _find(config.data_dir, args.case)
    who = args.who or getpass.getuser()
    path = write_request(config.data_dir / "requests", args.kind, c.case_id, who)
    what = ("the current pin set is measured again" if args.kind == "rerun"
            else "the case's next view starts a new pin set")
    print(f"requested for {c.case_id}: {what} (the running service takes {path.name} within a "
          "second, or at its next start)")
    return 0


def add_case_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("case", help="list, show, re-run a case, or start a new pin set")
    actions = p.add_subparsers(dest="action", required=True)
    for name, func, text in (("list", cmd_list, "the service's cases"),
                             ("show", cmd_show, "one case: pin sets, views, measurements")):
        a = actions.add_parser(name, help=text)
        a.add_argument("--config", type=Path, required=True, help="service configuration (TOML)")
        if name == "show":
            a.add_argument("case", help="case id (or its unique beginning)")
        a.set_defaults(func=func)
    for kind, text in (("rerun", "measure the current pin set again, without new X-rays"),
                       ("new-set", "the next view of the case starts a new pin set")):
        a = actions.add_parser(kind, help=text)
        a.add_argument("case", help="case id (or its unique beginning)")
        a.add_argument("--config", type=Path, required=True, help="service configuration (TOML)")
        a.add_argument("--who", help="who asks (audited; default: the user name)")
        a.set_defaults(func=cmd_request, kind=kind)
