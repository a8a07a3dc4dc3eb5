"""``slamtka bench service --out DIR``: latency and throughput of the whole service.

Runs the simulated theatre (:mod:`service.theatre`): ``slamtka serve`` on loopback, the
simulated C-arm's encoders on a pseudo-terminal, frames of the built-in phantom rendered at
the encoders' poses and sent by C-STORE as the C-arm exposes them, results C-STOREd to a
loopback OR display.

1. Latency: ``--cases`` surgeries one after the other, each view exposed when the C-arm
   holds at it; per case, the time from the start of the second view's C-STORE to the
   arrival of the structured report at the display.
2. Throughput: the same frames again as a burst (new UIDs, the original acquisition times,
   whose encoder readings are still in the link's history, as when a C-arm flushes its
   queue), every C-STORE back to back; cases per minute from the first C-STORE to the last
   report.

Prints the figures and writes ``service.json`` (with every case's angles against the
simulated truth).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from slamtka.sim.theatre import Theatre, TheatreCase, parse_angles

__all__ = ["add_service_bench_parser", "run_service_bench"]


def _angles_from_sr(sr) -> dict:
    """CTR/STR (deg) as the OR display reads them from the SR, or the refusal."""
    import highdicom as hd  # here: `slamtka` starts without it unless benchmarking

    from slamtka.service.dicom_sr import CODES

    report = hd.sr.Comprehensive3DSR.from_dataset(sr)
    groups = report.content.get_planar_roi_measurement_groups()
    if not groups:
        return {"status": "not_measured"}
    values = {m.name.value: m.value for m in groups[0].get_measurements() if m.derivation is None}
    return {"status": "measured", "ctr_deg": float(values[CODES["ctr"].value]),
            "str_deg": float(values[CODES["str"].value])}


def _row(case: TheatreCase, sr, arrived: float, started: float) -> dict:
    angles = _angles_from_sr(sr)
    row = {"case": case.index, "latency_s": arrived - started, **angles,
           "truth_ctr_deg": case.truth_ctr_deg, "truth_str_deg": case.truth_str_deg}
    if angles["status"] == "measured":
        row["ctr_error_deg"] = angles["ctr_deg"] - case.truth_ctr_deg
        row["str_error_deg"] = angles["str_deg"] - case.truth_str_deg
    return row


def _percentiles(values: list[float]) -> dict:
    v = np.asarray(values, float)
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
            "min": float(v.min()), "max": float(v.max())}


def run_service_bench(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    theatre = Theatre(out / "theatre", args.views, encoders=not args.no_encoders, seed=args.seed)
    print("preparing the phantom plan, calibration and frames ...", flush=True)
    theatre.prepare()
    t0 = time.perf_counter()
    cases = [theatre.make_case(i) for i in range(args.cases)]
    render_s = time.perf_counter() - t0
    print(f"rendered {args.cases * len(args.views)} frames in {render_s:.0f} s; starting the service",
          flush=True)
    theatre.start()
    try:
        sequential = []
        for case in cases:
            theatre.acquire(case)
            arrived, sr = theatre.wait_for_result(case)
            sequential.append(_row(case, sr, arrived, case.send_started[-1]))
            r = sequential[-1]
            print(f"  case {case.index:2d}: {r['latency_s']:.2f} s, "
                  + (f"CTR err {r['ctr_error_deg']:+.2f}, STR err {r['str_error_deg']:+.2f} deg"
                     if r["status"] == "measured" else "not measured"), flush=True)

        burst = [theatre.replay_case(case) for case in cases]
        start = time.monotonic()
        for case in burst:
            theatre.acquire(case, keep_times=True)
        arrivals = [theatre.wait_for_result(case) for case in burst]
        last = max(t for t, _ in arrivals)
        burst_rows = [_row(c, sr, t, c.send_started[-1]) for c, (t, sr) in zip(burst, arrivals)]
    finally:
        theatre.stop()

    latency = _percentiles([r["latency_s"] for r in sequential])
    burst_s = last - start
    measured = [r for r in sequential if r["status"] == "measured"]
    summary = {
        "cases": args.cases, "views_deg": list(args.views), "encoders": not args.no_encoders,
        "latency_s": latency, "throughput_cases_per_min": 60.0 * len(burst) / burst_s,
        "burst_seconds": burst_s, "measured": len(measured),
        "abs_ctr_error_deg": _percentiles([abs(r["ctr_error_deg"]) for r in measured]) if measured else None,
        "abs_str_error_deg": _percentiles([abs(r["str_error_deg"]) for r in measured]) if measured else None,
        "sequential": sequential, "burst": burst_rows,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version()},
        "render_seconds": render_s,
    }
    (out / "service.json").write_text(json.dumps(summary, indent=2))
    print(f"latency (second view C-STORE -> SR at the display), {args.cases} cases: median "
          f"{latency['median']:.2f} s, p90 {latency['p90']:.2f} s, max {latency['max']:.2f} s")
    print(f"throughput: {len(burst)} cases in {burst_s:.1f} s = "
          f"{summary['throughput_cases_per_min']:.1f} cases/min; measured {len(measured)}/{args.cases}")
    if measured:
        print(f"|CTR error| median {summary['abs_ctr_error_deg']['median']:.2f} deg, "
              f"|STR error| median {summary['abs_str_error_deg']['median']:.2f} deg")
    print(f"wrote {out / 'service.json'}")
    return 0


def add_service_bench_parser(kinds: argparse._SubParsersAction) -> None:
    p = kinds.add_parser("service", help="end-to-end latency and throughput of the service")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--cases", type=int, default=20)
    p.add_argument("--views", type=parse_angles, default=(-30.0, 30.0), help="orbital angles, deg")
    p.add_argument("--no-encoders", action="store_true",
                   help="no encoder link: views initialised from DICOM positioner angles")
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(func=run_service_bench)
