"""``slamtka bench link``: the figures of the C-arm link, measured against the simulated
C-arm over real pseudo-terminals, printed and written to ``link.json``.

- corruption: a fast stream through bit errors, dropped and duplicated bytes and noise bursts
  until the requested number of frames were corrupted; every accepted reading is compared
  with what the device sent (corrupted readings accepted), and every clean frame must arrive
  (a clean frame lost after a fault would mean resynchronisation took longer than a frame);
- latency at 100 Hz: device timestamp to history, on the device's true clock;
- stalls: a silent device detected after its last expected frame, and the maximum age rule
  audited with lookups while the device is silent;
- disconnect cycles: the device path removed and recreated; detection and reconnection
  delays, and open file descriptors and threads before and after.

The simulated C-arm runs in a child process, as a real device would be elsewhere: it shares
no interpreter lock with the driver, and the monotonic clock both read is the same, so its
timestamps give true latencies. Each section also records how late a 5 ms sleep woke up in
this process and the load average: on a shared machine, a long scheduling delay explains an
outlier that the driver did not cause.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import tempfile
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import serial

from slamtka.drivers.carm_sim import FaultSpec, MotionScript, SimulatedCArm
from slamtka.drivers.encoder_link import EncoderLink, LinkConfig, LinkState
from slamtka.drivers.reading_history import EncoderReading

# How long the bench waits for a link event before counting it as never having come. The
# figures are measured from the events' own timestamps and have their own targets, so this
# only tells slow from missing: a host loaded by other work must not turn slow into missing.
_EVENT_WAIT_S = 10.0
SCRIPT = MotionScript.from_orbital((0.0, -30.0, 30.0), hold_s=1.0, move_s=2.0)
CORRUPTION = "ber=3e-4,drop=5e-3,dup=5e-3,noise=0.2"


def _serve_sim(conn, kwargs: dict) -> None:
    """Child process: run a simulated C-arm and answer the parent's calls over ``conn``."""
    with SimulatedCArm(**kwargs) as sim:
        calls = {"stall": sim.stall, "vanish": sim.vanish, "reappear": sim.reappear,
                 "corrupt_line": sim.corrupt_line,
                 "last_reading": lambda: sim.last_reading_monotonic,
                 "frames_corrupted": lambda: sim.stats.faults.frames_corrupted,
                 "stats": lambda: sim.stats, "truth": lambda: sim.truth.table()}
        conn.send({"port": sim.port, "boot_monotonic": sim.boot_monotonic,
                   "clock_offset_us": sim.clock_offset_us, "identity": sim.identity})
        while (request := conn.recv())[0] != "stop":
            name, args = request
            try:
                conn.send(calls[name](*args))
            except Exception as exc:  # handed back to the parent
                conn.send(exc)
    conn.send(None)


class SimProcess:
    """The simulated C-arm in a child process, driven over a pipe."""

    def __init__(self, **sim_kwargs) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve_sim, args=(child, sim_kwargs), daemon=True)

    def __enter__(self) -> SimProcess:
        self._process.start()
        if not self._conn.poll(30.0):
            raise RuntimeError("the simulated C-arm process did not start")
        info = self._conn.recv()
        self.port, self.boot_monotonic = info["port"], info["boot_monotonic"]
        self.clock_offset_us, self.identity = info["clock_offset_us"], info["identity"]
        return self

    def __exit__(self, *exc_info) -> None:
        self._conn.send(("stop", ()))
        self._conn.recv()
        self._process.join(10.0)
        self._conn.close()

    def call(self, name: str, *args):
        self._conn.send((name, args))
        result = self._conn.recv()
        if isinstance(result, Exception):
            raise result
        return result


class _HostProbe:
    """Measures how late a 5 ms sleep wakes up while a section runs (scheduling delays)."""

    def __init__(self) -> None:
        self._late: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="host-probe", daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            t = time.monotonic()
            time.sleep(0.005)
            self._late.append(time.monotonic() - t - 0.005)

    def __enter__(self) -> _HostProbe:
        self._load = os.getloadavg()[0]
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join()

    def summary(self) -> dict:
        late = 1000.0 * np.array(self._late)
        return {"sleep_overshoot_p99_ms": float(np.percentile(late, 99)),
                "sleep_overshoot_max_ms": float(late.max()),
                "load_average_1min": [self._load, os.getloadavg()[0]]}


class _StateLog:
    """Records the link's state changes and lets the bench wait for one."""

    def __init__(self) -> None:
        self.states: list[LinkState] = []
        self._cond = threading.Condition()

    def __call__(self, state: LinkState) -> None:
        with self._cond:
            self.states.append(state)
            self._cond.notify_all()

    def mark(self) -> int:
        with self._cond:
            return len(self.states)

    def first_since(self, statuses: tuple[str, ...], t_monotonic: float) -> LinkState | None:
        """The first recorded state in ``statuses`` that began at or after ``t_monotonic``."""
        with self._cond:
            return next((s for s in self.states
                         if s.status in statuses and s.since_monotonic >= t_monotonic), None)

    def wait_for(self, status: str, since: int, timeout: float) -> LinkState | None:
        """The first state ``status`` recorded at or after index ``since``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for state in self.states[since:]:
                    if state.status == status:
                        return state
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)


def _ms(values: list[float] | np.ndarray) -> dict:
    v = 1000.0 * np.asarray(values, dtype=float)
    if v.size == 0:
        return {"n": 0}
    return {"n": int(v.size), "median_ms": float(np.median(v)), "p95_ms": float(np.percentile(v, 95)),
            "max_ms": float(v.max())}


def bench_corruption(target_corrupted: int, rate_hz: int, faults: str, seed: int) -> dict:
    spec = FaultSpec.parse(f"{faults},seed={seed}")
    received: list[tuple[int, int, tuple[float, ...]]] = []

    def keep(r: EncoderReading) -> None:
        received.append((r.sequence, r.device_time_us, tuple(r.joints.axes().values())))

    start = time.monotonic()
    with SimProcess(script=SCRIPT, record=True) as sim:
        config = LinkConfig(rate_hz=rate_hz, history_s=2.0)
        with EncoderLink(sim.port, config, on_reading=keep) as link:
            link.wait_connected(5.0)
            sim.call("corrupt_line", spec)  # noise sets in once the link streams
            while sim.call("frames_corrupted") < target_corrupted:
                time.sleep(0.5)
            sim.call("stall", 3600.0)  # the device falls quiet; let the link drain what is in flight
            count = -1
            while count != len(received):
                count = len(received)
                time.sleep(0.3)
            stats = link.stats
        truth, sim_stats = sim.call("truth"), sim.call("stats")
    seconds = time.monotonic() - start
    resolution = np.array([a.resolution for a in sim.identity.axes])
    seqs = np.array([r[0] for r in received], dtype=np.int64)
    rows = np.searchsorted(truth["sequence"], seqs).clip(0, len(truth["sequence"]) - 1)
    known = truth["sequence"][rows] == seqs
    counts = np.round(np.array([r[2] for r in received]) / resolution).astype(np.int64)
    exact = (known & (truth["device_time_us"][rows] == np.array([r[1] for r in received]))
             & (counts == truth["counts"][rows]).all(axis=1))
    accepted = np.zeros(len(truth["sequence"]), dtype=bool)
    accepted[rows[known]] = True
    clean = ~truth["corrupted"] & truth["delivered"]
    lost = clean & ~accepted
    # Longest run of clean frames lost in a row (0 when every clean frame was accepted).
    runs = np.diff(np.flatnonzero(np.diff(np.r_[0, lost.astype(np.int8), 0])))[::2]
    f = sim_stats.faults
    return {
        "faults": f"{faults},seed={seed}", "rate_hz": rate_hz, "seconds": seconds,
        "frames_sent": int(len(truth["sequence"])), "frames_corrupted": int(truth["corrupted"].sum()),
        "noise_bursts": f.noise_bursts, "bits_flipped": f.bits_flipped, "bytes_dropped": f.bytes_dropped,
        "bytes_duplicated": f.bytes_duplicated, "device_overruns": sim_stats.overruns,
        "readings_accepted": int(len(received)),
        "corrupted_readings_accepted": int((~exact).sum()),
        "corrupted_frames_accepted_intact": int((accepted & truth["corrupted"]).sum()),
        "clean_frames": int(clean.sum()), "clean_frames_lost": int(lost.sum()),
        "max_clean_frames_lost_in_a_row": int(runs.max()) if runs.size else 0,
        "parser": vars(stats.parser),
        "rejected": {"malformed": stats.rejected.malformed, "range": stats.rejected.range,
                     "rate": stats.rejected.rate, "duplicate": stats.rejected.duplicate},
    }


def bench_latency(seconds: float, rate_hz: int) -> dict:
    rows: list[tuple[float, int, float]] = []

    def keep(r: EncoderReading) -> None:
        rows.append((r.received_monotonic, r.device_time_us, (r.received_utc - r.time_utc).total_seconds()))

    with SimProcess(script=SCRIPT) as sim:
        with EncoderLink(sim.port, LinkConfig(rate_hz=rate_hz), on_reading=keep) as link:
            link.wait_connected(5.0)
            time.sleep(seconds)
    data = np.array(rows[10:])  # skip the start, while the clock estimate settles
    sampled = sim.boot_monotonic + (data[:, 1] - sim.clock_offset_us) * 1e-6
    latency = data[:, 0] - sampled
    return {"rate_hz": rate_hz, "seconds": seconds, "readings": int(len(data)),
            "achieved_rate_hz": float((len(data) - 1) / (data[-1, 0] - data[0, 0])),
            "latency": _ms(latency), "clock_mapping_error": _ms(np.abs(data[:, 2] - latency))}


def _audit(link: EncoderLink, max_age: float, tally: dict, rng: np.random.Generator) -> None:
    """One lookup of each kind; count refusals and any reading older than the maximum age."""
    now = time.monotonic()
    now_utc = datetime.now(UTC)
    latest = link.latest()
    tally["lookups"] += 2
    if latest is None:
        tally["refused"] += 1
    elif latest.age_s(now) > max_age:
        tally["violations"] += 1
    past = now_utc - timedelta(seconds=float(rng.uniform(0.0, 0.5)))
    found = link.reading_at(past)
    if found is None:
        tally["refused"] += 1
    elif abs((found.time_utc - past).total_seconds()) > max_age:
        tally["violations"] += 1


def bench_stalls(stalls: int, rate_hz: int, seed: int, stall_s: float = 0.3) -> dict:
    rng = np.random.default_rng(seed)
    events = _StateLog()
    config = LinkConfig(rate_hz=rate_hz)
    period = 1.0 / rate_hz
    detect, resume, failures = [], [], 0
    tally = {"lookups": 0, "refused": 0, "violations": 0}
    with SimProcess(script=SCRIPT) as sim:
        with EncoderLink(sim.port, config, on_state=events) as link:
            link.wait_connected(5.0)
            for _ in range(stalls):
                link.wait_reading(_EVENT_WAIT_S)
                time.sleep(0.1)
                mark = events.mark()
                began = sim.call("stall", stall_s)
                last_expected = sim.call("last_reading") + period
                while time.monotonic() < began + stall_s:
                    _audit(link, config.max_age_s, tally, rng)
                    time.sleep(0.002)
                silent = events.wait_for("silent", mark, _EVENT_WAIT_S)
                back = events.wait_for("connected", mark, _EVENT_WAIT_S)
                if silent is None or back is None:
                    failures += 1
                    continue
                detect.append(silent.since_monotonic - last_expected)
                resume.append(back.since_monotonic - (began + stall_s))
    return {"stalls": stalls, "stall_s": stall_s, "rate_hz": rate_hz, "failures": failures,
            "silent_detected_after_last_expected_frame": _ms(detect),
            "streaming_again_after_stall_end": _ms(resume), "max_age_audit": tally,
            "max_age_s": config.max_age_s}


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def bench_disconnects(cycles: int, rate_hz: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    events = _StateLog()
    config = LinkConfig(rate_hz=rate_hz)
    period = 1.0 / rate_hz
    detect_expected, detect_vanish, reconnect, failures, stale = [], [], [], 0, 0
    warmup = 3
    with tempfile.TemporaryDirectory(prefix="slamtka-link-") as tmp:
        with SimProcess(script=SCRIPT, port_link=Path(tmp) / "carm") as sim:
            with EncoderLink(sim.port, config, on_state=events) as link:
                link.wait_connected(5.0)
                for cycle in range(warmup + cycles):
                    if cycle == warmup:
                        fds_before, threads_before = _open_fds(), threading.active_count()
                    previous = link.wait_reading(_EVENT_WAIT_S)
                    link.wait_reading(_EVENT_WAIT_S, previous.sequence)
                    mark = events.mark()
                    vanished = sim.call("vanish")
                    last_frame = sim.call("last_reading")
                    gone = events.wait_for("disconnected", mark, _EVENT_WAIT_S)
                    # A device that hiccups just before it vanishes is first reported silent.
                    noticed = events.first_since(("silent", "disconnected"), last_frame)
                    absent = float(np.exp(rng.uniform(np.log(0.01), np.log(0.5))))
                    time.sleep(max(0.0, vanished + absent - time.monotonic()))
                    if absent > config.max_age_s and link.latest() is not None:
                        stale += 1
                    mark = events.mark()
                    back = sim.call("reappear")
                    connected = events.wait_for("connected", mark, _EVENT_WAIT_S)
                    if cycle < warmup:
                        continue
                    if gone is None or connected is None:
                        failures += 1
                        continue
                    detect_expected.append(noticed.since_monotonic - (last_frame + period))
                    detect_vanish.append(gone.since_monotonic - vanished)
                    reconnect.append(connected.since_monotonic - back)
                link.wait_reading(_EVENT_WAIT_S)
                fds_after, threads_after = _open_fds(), threading.active_count()
    return {"cycles": cycles, "rate_hz": rate_hz, "absence_s": "log-uniform 0.01-0.5", "failures": failures,
            "detected_after_last_expected_frame": _ms(detect_expected),
            "detected_after_vanishing": _ms(detect_vanish), "reconnected_after_return": _ms(reconnect),
            "fds_before": fds_before, "fds_after": fds_after, "threads_before": threads_before,
            "threads_after": threads_after, "stale_readings_while_gone": stale}


def _figures(r: dict, corrupted_target: int) -> list[dict]:
    c, lat, st, dc = r["corruption"], r["latency"], r["stalls"], r["disconnects"]
    detect_max = max(st["silent_detected_after_last_expected_frame"].get("max_ms", np.inf),
                     dc["detected_after_last_expected_frame"].get("max_ms", np.inf))
    rows = [
        ("frames with injected corruption", c["frames_corrupted"], f">= {corrupted_target}",
         c["frames_corrupted"] >= corrupted_target),
        ("corrupted readings accepted", c["corrupted_readings_accepted"], "0",
         c["corrupted_readings_accepted"] == 0),
        ("clean frames lost after noise (resync within one frame)", c["clean_frames_lost"], "0",
         c["clean_frames_lost"] == 0),
        ("silent/vanished device detected after last expected frame, max ms", round(detect_max, 1),
         "<= 100", detect_max <= 100),
        ("reconnected after the device returned, max ms",
         round(dc["reconnected_after_return"].get("max_ms", np.inf), 1), "<= 1000",
         dc["reconnected_after_return"].get("max_ms", np.inf) <= 1000 and dc["failures"] == 0),
        (f"fd / thread growth over {dc['cycles']} disconnect cycles",
         f"{dc['fds_after'] - dc['fds_before']} / {dc['threads_after'] - dc['threads_before']}", "0 / 0",
         dc["fds_after"] == dc["fds_before"] and dc["threads_after"] == dc["threads_before"]),
        ("readings older than the maximum age handed out",
         st["max_age_audit"]["violations"] + dc["stale_readings_while_gone"], "0",
         st["max_age_audit"]["violations"] + dc["stale_readings_while_gone"] == 0),
        (f"median latency at {lat['rate_hz']} Hz, ms", round(lat["latency"]["median_ms"], 2), "< 5",
         lat["latency"]["median_ms"] < 5),
    ]
    return [{"figure": n, "value": v, "target": t, "met": bool(m)} for n, v, t, m in rows]


def run_link_bench(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    sections = {
        "corruption": (f"streaming at {args.fast_rate_hz} Hz until {args.corrupted_frames} frames are "
                       "corrupted", lambda: bench_corruption(args.corrupted_frames, args.fast_rate_hz,
                                                             args.faults, args.seed)),
        "latency": (f"{args.latency_s:g} s at 100 Hz", lambda: bench_latency(args.latency_s, 100)),
        "stalls": (f"{args.stalls} stalls", lambda: bench_stalls(args.stalls, 100, args.seed)),
        "disconnects": (f"{args.cycles} disconnect cycles",
                        lambda: bench_disconnects(args.cycles, 100, args.seed)),
    }
    results = {}
    for name, (what, run) in sections.items():
        print(f"{name}: {what} ...", flush=True)
        with _HostProbe() as probe:
            results[name] = run()
        results[name]["host"] = probe.summary()
    figures = _figures(results, args.corrupted_frames)
    doc = {"format": "slamtka-bench-link/1", "created_utc": datetime.now(UTC).isoformat(),
           "environment": {"python": platform.python_version(), "pyserial": serial.__version__,
                           "platform": platform.platform(), "cpus": os.cpu_count()},
           "link_config": LinkConfig().to_config(), "figures": figures, **results}
    (args.out / "link.json").write_text(json.dumps(doc, indent=2))
    width = max(len(f["figure"]) for f in figures)
    print(f"\n{'figure':<{width}}  {'value':>12}  {'target':>8}  met")
    for f in figures:
        met = "yes" if f["met"] else "NO"
        print(f"{f['figure']:<{width}}  {str(f['value']):>12}  {f['target']:>8}  {met}")
    c = results["corruption"]
    print(f"\n{c['frames_sent']} frames sent, {c['readings_accepted']} readings accepted; parser rejected "
          f"{c['parser']['header_errors']} headers and {c['parser']['crc_errors']} frame CRCs; "
          f"latency p95 {results['latency']['latency']['p95_ms']:.2f} ms; "
          f"reconnect median {results['disconnects']['reconnected_after_return']['median_ms']:.0f} ms")
    worst = max(results.values(), key=lambda r: r["host"]["sleep_overshoot_max_ms"])["host"]
    print(f"host scheduling: a 5 ms sleep overshot by up to {worst['sleep_overshoot_max_ms']:.0f} ms "
          f"(load average {max(worst['load_average_1min']):.1f} on {os.cpu_count()} CPUs)")
    print(f"wrote {args.out / 'link.json'}")
    return 0 if all(f["met"] for f in figures) else 1


def add_link_bench(kinds: argparse._SubParsersAction) -> None:
    p = kinds.add_parser("link", help="the C-arm encoder link against the simulated C-arm")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--corrupted-frames", type=int, default=100_000,
                   help="stream until this many frames were corrupted")
    p.add_argument("--faults", default=CORRUPTION, help="line faults for the corruption run")
    p.add_argument("--fast-rate-hz", type=int, default=4000, help="stream rate of the corruption run")
    p.add_argument("--latency-s", type=float, default=20.0, help="seconds of 100 Hz streaming")
    p.add_argument("--stalls", type=int, default=50)
    p.add_argument("--cycles", type=int, default=1000, help="disconnect cycles")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run_link_bench)
