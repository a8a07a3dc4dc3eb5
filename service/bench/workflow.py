"""``slamtka bench workflow --out DIR``: the re-measurement loop, end to end.

Runs the simulated theatre (:mod:`service.theatre`: ``slamtka serve`` on loopback, the
simulated C-arm's encoders on a pseudo-terminal, frames rendered at the encoders' poses,
results C-STOREd to a loopback OR display).

1. Re-pinning. Per case: two views, measured; then the pins are seen again unmoved (two
   views: they must stay in the pin set) and turned, one placement after the other, by
   +2, -2, +5, -5 deg about the medio-lateral axis and the same about the antero-posterior
   axis (through the pins' midpoint), two new views after each. Every measurement report
   the display receives is checked: a *wrong angle* is a report whose views mix pin
   placements, or whose CTR/STR is more than ``--wrong-deg`` off the truth of its
   placement. Each re-pin should start a new set measured from its own two views.
2. Stalled cases: a lone view, an unusable view (no geometry), no plan for the patient,
   views too close in angle, a refusal (two views of a patient without a plan), encoder
   and header angles 60 deg apart, and a C-arm clock 1 s ahead of the encoder stream: the
   time from the C-STORE of the (last) view to the arrival of the display's status (or
   refusal) report.

Prints the figures and writes ``workflow.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

from pydicom.uid import generate_uid

from slamtka.bench.service import _angles_from_sr, _percentiles
from slamtka.service.dicom_sr import CODES
from slamtka.service.display import STATUS_SERIES
from slamtka.sim.theatre import Theatre, TheatreCase, _evidence, parse_angles

__all__ = ["add_workflow_bench_parser", "run_workflow_bench"]

REPINS = (("none", 0.0), ("ml", 2.0), ("ml", -2.0), ("ml", 5.0), ("ml", -5.0),
          ("ap", 2.0), ("ap", -2.0), ("ap", 5.0), ("ap", -5.0))


def _wait_status(theatre: Theatre, study_uid: str, after: float, timeout: float = 10.0,
                 saying: str = "") -> tuple[float, str] | None:
    """(arrival, notes) of the first status report of ``study_uid`` arriving after ``after``
    (monotonic) whose notes contain ``saying``, or None within ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for t, ds in list(theatre.display.received):
            if (t >= after and ds.StudyInstanceUID == study_uid and ds.Modality == "SR"
                    and ds.SeriesDescription == STATUS_SERIES and saying in _text_items(ds)):
                return t, _text_items(ds)
        time.sleep(0.02)
    return None


def _text_items(ds) -> str:
    """The report's notes in words (:data:`service.dicom_sr.CODES`), joined."""
    notes = {CODES[k].value for k in ("reason", "action", "history", "service_status")}
    return " | ".join(str(item.TextValue) for item in ds.ContentSequence
                      if getattr(item, "ValueType", "") == "TEXT"
                      and item.ConceptNameCodeSequence[0].CodeValue in notes)


def _placements(theatre: Theatre, case: TheatreCase) -> list[tuple[str, float, TheatreCase]]:
    """The case's placements in order: each re-pin turns the previous placement."""
    out, current = [], case
    for axis, angle in REPINS:
        nxt = theatre.repin(current, "ml", 0.0) if axis == "none" else theatre.repin(
            current, axis, angle)
        out.append((axis, angle, nxt))
        current = nxt
    return out


def _repin_rows(theatre: Theatre, case: TheatreCase,
                truth_of: dict[str, tuple[tuple[int, int], TheatreCase]]) -> list[dict]:
    """Measure the case, then every re-pin; one row per placement after the first.
    ``truth_of`` gets every frame sent: (case, placement) and the placement's truth."""
    truth_of.update({f.sop_instance_uid: ((case.index, 0), case) for f in case.frames})
    theatre.acquire(case)
    theatre.wait_for_result(case, exact=True)
    rows, placement = [], 0
    in_set = {f.sop_instance_uid for f in case.frames}  # the frames of the current placement
    for axis, angle, placed in _placements(theatre, case):
        moved = axis != "none"
        placement += moved
        truth_of.update({f.sop_instance_uid: ((case.index, placement), placed)
                         for f in placed.frames})
        new = {f.sop_instance_uid for f in placed.frames}
        in_set = new if moved else in_set | new
        sent = time.monotonic()
        theatre.acquire(placed)
        status = _wait_status(theatre, case.study_uid, sent, timeout=10.0)
        found = theatre.display.wait(
            lambda ds, in_set=in_set: ds.Modality == "SR" and ds.SeriesDescription != STATUS_SERIES
            and ds.StudyInstanceUID == case.study_uid and _evidence(ds) == in_set, 60.0)
        arrived, angles = (found[0][0], _angles_from_sr(found[0][1])) if found else (
            None, {"status": "no report"})
        row = {"case": case.index, "axis": axis, "turn_deg": angle, "measured": angles,
               "truth_ctr_deg": placed.truth_ctr_deg, "truth_str_deg": placed.truth_str_deg,
               "status_message": status[1] if status else None,
               "status_latency_s": (status[0] - placed.send_started[0]) if status else None,
               "result_latency_s": None if arrived is None else arrived - placed.send_started[-1],
               "own_views_measured": arrived is not None}
        if angles["status"] == "measured":
            row["ctr_error_deg"] = angles["ctr_deg"] - placed.truth_ctr_deg
            row["str_error_deg"] = angles["str_deg"] - placed.truth_str_deg
        rows.append(row)
    return rows


def _wrong_reports(theatre: Theatre, truth_of: dict[str, tuple[tuple[int, int], TheatreCase]],
                   wrong_deg: float) -> list[dict]:
    """Every measurement report at the display whose views mix placements or whose angles
    are further than ``wrong_deg`` from the truth of its placement."""
    wrong = []
    for _, ds in theatre.display.received:
        if ds.Modality != "SR" or ds.SeriesDescription == STATUS_SERIES:
            continue
        uids = _evidence(ds)
        placements = {truth_of[u][0] for u in uids if u in truth_of}
        angles = _angles_from_sr(ds)
        if angles["status"] != "measured" or not placements:
            continue
        if len(placements) > 1:
            wrong.append({"why": "views of different placements", "views": sorted(uids)})
            continue
        placed = truth_of[next(iter(uids))][1]
        err = max(abs(angles["ctr_deg"] - placed.truth_ctr_deg),
                  abs(angles["str_deg"] - placed.truth_str_deg))
        if err > wrong_deg:
            wrong.append({"why": f"{err:.2f} deg off the truth", "views": sorted(uids)})
    return wrong


def _stalled(theatre: Theatre, template: TheatreCase) -> list[dict]:
    """Each stalled-case situation once: (situation, latency to the display, message)."""
    long_ago = datetime.now(UTC) - timedelta(hours=2)  # no encoder reading then

    def variant(**changes) -> TheatreCase:
        study = generate_uid(prefix=None)
        frames = [replace(f, study_uid=study, series_uid=study + ".1",
                          sop_instance_uid=generate_uid(prefix=None), **changes)
                  for f in template.frames]
        return replace(template, study_uid=study, frames=frames, send_started=[])

    rows = []

    def run(situation: str, case: TheatreCase, n_views: int, keep_times: bool,
            saying: str) -> None:
        case.frames = case.frames[:n_views]
        theatre.acquire(case, keep_times=keep_times)
        start = case.send_started[-1]
        if situation.startswith("refused"):
            try:
                arrived, sr = theatre.wait_for_result(case, timeout=30.0)
                got = (arrived, _text_items(sr))
            except TimeoutError:
                got = None
        else:
            got = _wait_status(theatre, case.study_uid, start, timeout=30.0, saying=saying)
        rows.append({"situation": situation, "latency_s": None if got is None else got[0] - start,
                     "message": None if got is None else got[1]})

    run("lone view", variant(), 1, False, "one view so far")
    run("unusable view (no geometry)", variant(primary_angle_deg=None, secondary_angle_deg=None,
                                               acquisition_datetime=long_ago), 1, True,
        "cannot be used")
    run("no plan for the patient", variant(patient_id="NO-PLAN-1"), 1, False, "No plan")
    close = variant(acquisition_datetime=long_ago)
    close.frames[1] = replace(close.frames[0], sop_instance_uid=generate_uid(prefix=None),
                              primary_angle_deg=close.frames[0].primary_angle_deg + 5.0)
    run("views too close", close, 2, True, "too close")
    run("refused (two views, no plan)", variant(patient_id="NO-PLAN-2"), 2, False, "no plan")
    askew = variant()
    askew.frames = [replace(f, primary_angle_deg=f.primary_angle_deg + 60.0) for f in askew.frames]
    run("encoder and header angles 60 deg apart", askew, 1, False, "not used")
    theatre.clock_offset_s = 1.0
    try:
        run("C-arm clock 1 s ahead of the encoders", variant(), 1, False, "C-arm clock")
    finally:
        theatre.clock_offset_s = 0.0
    return rows


def run_workflow_bench(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    theatre = Theatre(out / "theatre", args.views, hold_s=args.hold_s, move_s=args.move_s,
                      seed=args.seed)
    print("preparing the phantom plan, calibration and frames ...", flush=True)
    theatre.prepare()
    cases = [theatre.make_case(i) for i in range(args.cases)]
    theatre.start()
    truth_of: dict[str, tuple[tuple[int, int], TheatreCase]] = {}
    rows: list[dict] = []
    try:
        stalled = _stalled(theatre, cases[0] if cases else theatre.make_case(0))
        for case in cases:
            case_rows = _repin_rows(theatre, case, truth_of)
            rows += case_rows
            for r in case_rows:
                print(f"  case {r['case']:2d} {r['axis']:4s} {r['turn_deg']:+4.0f} deg: "
                      + (f"CTR err {r['ctr_error_deg']:+.2f}, STR err {r['str_error_deg']:+.2f}"
                         if "ctr_error_deg" in r else r["measured"]["status"])
                      + f"; display: {r['status_message']}", flush=True)
        time.sleep(2.0)  # any report still on its way
        wrong = _wrong_reports(theatre, truth_of, args.wrong_deg)
    finally:
        theatre.stop()

    repins = [r for r in rows if r["axis"] != "none"]
    same = [r for r in rows if r["axis"] == "none"]
    errors = [max(abs(r["ctr_error_deg"]), abs(r["str_error_deg"])) for r in repins
              if "ctr_error_deg" in r]
    took = [r["result_latency_s"] for r in rows if r["result_latency_s"] is not None]
    latency = _percentiles(took) if took else None
    waits = [r["status_latency_s"] for r in repins if r["status_latency_s"] is not None]
    summary = {
        "cases": args.cases, "views_deg": list(args.views), "wrong_angle_threshold_deg": args.wrong_deg,
        "wrong_angles": len(wrong), "wrong": wrong,
        "repins": len(repins), "repins_measured_from_own_views": sum(r["own_views_measured"]
                                                                      for r in repins),
        "repin_abs_error_deg": _percentiles(errors) if errors else None,
        "unmoved_kept_in_set": sum(r["own_views_measured"] for r in same), "unmoved": len(same),
        "stalled": stalled, "rows": rows, "result_latency_s": latency,
        "status_latency_s": _percentiles(waits) if waits else None,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version()},
    }
    (out / "workflow.json").write_text(json.dumps(summary, indent=2, default=str))
    print(f"re-pins: {len(repins)} ({args.cases} cases x {len(REPINS) - 1}); measured from "
          f"their own views: {summary['repins_measured_from_own_views']}; wrong angles at the "
          f"display: {len(wrong)}")
    if errors:
        e = summary["repin_abs_error_deg"]
        print(f"new sets: worst-angle |error| median {e['median']:.2f}, p90 {e['p90']:.2f}, "
              f"max {e['max']:.2f} deg")
    print(f"unmoved pins seen again: kept in their set {summary['unmoved_kept_in_set']}/{len(same)}")
    for s in stalled:
        took = "no message" if s["latency_s"] is None else f"{s['latency_s']:.2f} s"
        print(f"  {s['situation']}: {took}: {s['message']}")
    if waits:
        print(f"re-pin first view -> 'new pin set' status at the display: median "
              f"{summary['status_latency_s']['median']:.2f} s, max {summary['status_latency_s']['max']:.2f} s")
    if latency:
        print(f"result latency (last view C-STORE -> report): median {latency['median']:.2f} s, "
              f"max {latency['max']:.2f} s")
    print(f"wrote {out / 'workflow.json'}")
    return 0 if not wrong else 1


def add_workflow_bench_parser(kinds: argparse._SubParsersAction) -> None:
    p = kinds.add_parser("workflow", help="the re-measurement loop: re-pinning, stalled cases")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--cases", type=int, default=10, help="re-pinned cases (0: stalled cases only)")
    p.add_argument("--views", type=parse_angles, default=(-30.0, 30.0), help="orbital angles, deg")
    p.add_argument("--hold-s", type=float, default=0.8, help="C-arm hold at each view, s")
    p.add_argument("--move-s", type=float, default=1.6, help="C-arm move between views, s")
    p.add_argument("--wrong-deg", type=float, default=1.0,
                   help="a reported angle this far off its placement's truth is wrong")
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(func=run_workflow_bench)
