"""Faults, durability and soak of the whole service, counted: items of ``slamtka bench hardening``.

Unlike the receiver items of :mod:`service.bench_hardening`, these run ``slamtka serve`` as
its own process in the simulated theatre (:mod:`service.theatre`): a C-arm client on
loopback, an OR display receiving the results, and for the serial items the simulated
C-arm's encoders on a pseudo-terminal.

- ``crash``: stores while the service is killed (SIGKILL) at random moments and restarted;
  every acknowledged instance must be in the spool (and the audit log) afterwards, no partial
  file visible, every case completed with exactly one result per input set, delivered once
  (by SOP Instance UID), and every re-sent instance recognised as a duplicate.
- ``destination_down``: the OR display is down while cases are measured and the service is
  killed and restarted; the results wait in the queue and all arrive when it returns.
- ``serial_faults``: the encoder link stalls or loses bytes at the moment of exposure; such a
  view is initialised from its DICOM positioner angles (or refused when it has none) and the
  result says which, never an encoder reading from another moment.
- ``soak``: one frame a second and one malformed input a minute for a given time; the
  service's resident memory and open file descriptors over time.

The frames of the durability items are small (64 x 64) and their patient has no plan, so each
run is a quick, complete "not measured" run with every result object; the serial item uses
phantom frames and measures them.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import psutil
import pydicom
from pydicom.uid import generate_uid

from slamtka.bench.hardening import Tally
from slamtka.bench.hostile import (
    Dropped,
    RawAssociation,
    dataset_bytes,
    element_length_cases,
    malformed_pdus,
    pixel_length_cases,
    truncations,
    with_uid,
)
from slamtka.drivers.carm_sim import FaultSpec
from slamtka.service.audit import read_audit
from slamtka.service.cases import case_id_of, run_id_of
from slamtka.service.display import STATUS_SERIES
from slamtka.service.frames import Frame
from slamtka.service.spool import entry_id
from slamtka.sim.theatre import CARM_AE, PATIENT_ID, SERVICE_AE, ResultCollector, Theatre

__all__ = ["FAULT_ITEMS", "run_fault_item", "crash", "destination_down", "serial_faults", "soak",
           "SoakFigures", "SmallCase", "small_case", "CArmClient", "running_theatre"]

FAULT_ITEMS = ("crash", "destination_down", "serial_faults")
# Fast retries, and never give up, so that a result waits for as long as a bench keeps a
# destination down; the defaults (2 s doubling to 300 s, 50 attempts) are for hospitals.
_FAST_SENDER = {"SLAMTKA_SENDER_RETRY_INITIAL_S": "0.2", "SLAMTKA_SENDER_RETRY_MAX_S": "1.0",
                "SLAMTKA_SENDER_MAX_ATTEMPTS": "100000"}
_SPOOLED = re.compile(r"^[0-9a-f]{40}\.(dcm|json)$")
_OBJECTS_PER_RUN = 3  # the structured report and one image per view of a two-view case
MEMORY_DRIFT_LIMIT_MB = 64.0  # resident memory growth after the first minute of a soak
FD_GROWTH_LIMIT = 8  # open file descriptors more at the end of a soak than after its first minute


# -- frames, client, theatre -------------------------------------------------------------

@dataclass
class SmallCase:
    """A case of small frames (no plan for its patient): its views as sent on the wire."""

    patient_id: str
    study_uid: str
    views: list[tuple[bytes, str]]  # (dataset, SOP Instance UID)

    @property
    def uids(self) -> list[str]:
        return [uid for _, uid in self.views]

    def folder(self, theatre: Theatre) -> Path:
        return _data(theatre) / "output" / case_id_of(self.patient_id, self.study_uid, "R")

    def result(self, theatre: Theatre) -> Path:
        """The result document of the run of all its views."""
        return self.folder(theatre) / run_id_of(self.uids) / "result.json"


def small_case(tag: str, index: int, angles_deg: tuple[float, ...] = (-30.0, 30.0)) -> SmallCase:
    """Patient ``tag-index``, one 64 x 64 frame per angle (positioner angles, no encoders)."""
    rng = np.random.default_rng(index)
    patient, study, series = f"{tag}-{index}", generate_uid(), generate_uid()
    views = []
    for k, angle in enumerate(angles_deg, start=1):
        frame = Frame(pixels=rng.integers(0, 4000, (64, 64)).astype(np.uint16),
                      imager_pixel_spacing_mm=(0.3, 0.3), primary_angle_deg=angle,
                      secondary_angle_deg=0.0, sid_mm=1000.0, sod_mm=620.0,
                      acquisition_datetime=datetime.now(UTC), patient_id=patient,
                      study_uid=study, series_uid=series, laterality="R", bits_stored=12,
                      instance_number=k)
        views.append((dataset_bytes(frame), frame.sop_instance_uid))
    return SmallCase(patient, study, views)


class CArmClient:
    """Stores like a C-arm: one association, opened again after the service went away."""

    def __init__(self, port: int):
        self.port = port
        self._assoc: RawAssociation | None = None

    def store(self, data: bytes, uid: str, attempts: int = 2) -> int | None:
        """The C-STORE status, or None when no answer came (the instance is not acknowledged).

        Like a C-arm, it sends again once on a fresh association when the first went quiet
        or was dropped (the service recognises an instance it already holds)."""
        for _ in range(attempts):
            try:
                if self._assoc is None:
                    self._assoc = RawAssociation(self.port, calling=CARM_AE, called=SERVICE_AE,
                                                 timeout_s=10.0).associate()
                return self._assoc.store(data, uid)
            except (Dropped, OSError):
                self.close()
        return None

    def close(self) -> None:
        if self._assoc is not None:
            self._assoc.release()
            self._assoc = None


@contextmanager
def running_theatre(root: Path, encoders: bool = False, **kwargs) -> Iterator[Theatre]:
    """The service (fast sender retries), an OR display and optionally the C-arm's encoders.

    The display's pynetdicom logs every association a killed service leaves half-sent, with a
    traceback; those are expected here, so they are kept out of the bench's output."""
    theatre = Theatre(root, encoders=encoders, **kwargs)
    theatre.environ.update(_FAST_SENDER)
    theatre.prepare()
    quiet = logging.getLogger("pynetdicom")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    theatre.start()
    try:
        yield theatre
    finally:
        theatre.stop()
        quiet.setLevel(level)


def _data(theatre: Theatre) -> Path:
    return theatre.root / "data"


def _wait(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.2) -> bool:
    deadline = time.monotonic() + timeout_s
    while not (ok := predicate()) and time.monotonic() < deadline:
        time.sleep(poll_s)
    return ok


def _delivered(display: ResultCollector) -> dict[str, Counter]:
    """How often each result object (status reports aside) arrived at the display, per study."""
    out: dict[str, Counter] = {}
    for _, ds in list(display.received):
        if ds.get("SeriesDescription") == STATUS_SERIES:
            continue
        out.setdefault(str(ds.StudyInstanceUID), Counter())[str(ds.SOPInstanceUID)] += 1
    return out


def _all_delivered(display: ResultCollector, cases: list[SmallCase]) -> bool:
    got = _delivered(display)
    return all(len(got.get(c.study_uid, ())) >= _OBJECTS_PER_RUN for c in cases)


def _partial_files(data: Path) -> list[str]:
    """Files in the spool and the send queue that are not complete entries or jobs."""
    spool = [p.name for p in (data / "spool" / "instances").iterdir() if not _SPOOLED.match(p.name)]
    queue = [p.name for folder in ("pending", "failed") for p in (data / "queue" / folder).iterdir()
             if p.suffix != ".json" or p.name.startswith(".")]
    return spool + queue


# -- faults and durability ---------------------------------------------------------------

def crash(root: Path, stores: int, kills: int, seed: int = 0) -> Tally:
    """``stores`` instances (two-view cases) while the service is killed ``kills`` times."""
    rng = np.random.default_rng(seed)
    cases = [small_case("CRASH", i) for i in range((stores + 1) // 2)]
    queue = deque(view for case in cases for view in case.views)
    data_of = {uid: data for data, uid in queue}
    acked: set[str] = set()
    resent: list[str] = []
    refused: list[str] = []
    with running_theatre(root) as theatre:
        since_restart, killed, sending = [0], [], threading.Event()
        sending.set()

        def killer() -> None:
            moments = np.random.default_rng(seed + 1)  # its own: Generators are not thread-safe
            per_life = max(1, 2 * stores // max(kills, 1))
            for _ in range(kills):
                target = int(moments.integers(0, per_life + 1))
                _wait(lambda target=target: since_restart[0] >= target or not sending.is_set(), 600.0, 0.005)
                time.sleep(float(moments.uniform(0.0, 0.2 if sending.is_set() else 1.5)))
                theatre.stop_service(kill=True)
                killed.append(time.monotonic())
                since_restart[0] = 0
                theatre.start_service()

        thread = threading.Thread(target=killer, name="killer", daemon=True)
        thread.start()
        client = CArmClient(theatre.port)
        while queue:
            data, uid = queue[0]
            status = client.store(data, uid)
            if status is None:  # the service went away mid-store: send it again
                if not thread.is_alive() and theatre.service.poll() is not None:
                    raise RuntimeError(f"the service is down for good; see {root / 'service.log'}")
                time.sleep(0.05)
                continue
            queue.popleft()
            if status != 0x0000:
                refused.append(f"{uid}: 0x{status:04X}")
                continue
            if uid in acked:
                resent.append(uid)
            acked.add(uid)
            since_restart[0] += 1
            if rng.random() < 0.05:  # the C-arm sends an earlier image again
                again = sorted(acked)[int(rng.integers(0, len(acked)))]
                queue.append((data_of[again], again))
        client.close()
        sending.clear()
        thread.join()
        _wait(lambda: all(c.result(theatre).is_file() for c in cases), 120.0 + 2.0 * len(cases))
        _wait(lambda: _all_delivered(theatre.display, cases), 120.0)
        theatre.stop_service()
        tally = _crash_checks(theatre, cases, acked, resent)
    tally.notes.update(kills=len(killed), acknowledged=len(acked), resent_acknowledged=len(resent),
                       refused_valid=refused[:10])
    tally.failures += len(refused) + max(0, kills - len(killed))
    return tally


def _crash_checks(theatre: Theatre, cases: list[SmallCase], acked: set[str],
                  resent: list[str]) -> Tally:
    """One count per acknowledged instance (lost or not), and every other failure."""
    tally, data = Tally(), _data(theatre)
    audit = list(read_audit(data / "audit.jsonl"))
    audited = {e.get("sop_instance_uid") for e in audit if e["event"] in ("received", "duplicate")}
    duplicates = Counter(e["sop_instance_uid"] for e in audit if e["event"] == "duplicate")
    processed = Counter((e["case_id"], e["run_id"]) for e in audit if e["event"] == "processed")
    lost = 0
    for uid in sorted(acked):
        path = data / "spool" / "instances" / f"{entry_id(uid)}.dcm"
        kept = path.is_file() and str(pydicom.dcmread(
            path, stop_before_pixels=True).SOPInstanceUID) == uid and uid in audited
        tally.count(not kept, f"acknowledged {uid} lost")
        lost += not kept
    unrecognised = [u for u, n in Counter(resent).items() if duplicates[u] < n]
    partial = _partial_files(data)
    got = _delivered(theatre.display)
    figures = Counter()
    for case in cases:
        folder, sent = case.folder(theatre), got.get(case.study_uid, Counter())
        figures["cases_incomplete"] += not case.result(theatre).is_file()
        figures["extra_results"] += max(0, len(list(folder.glob("*/result.json"))) - 1)
        figures["runs_processed_twice"] += sum(n > 1 for (c, _), n in processed.items()
                                               if c == folder.name)
        figures["cases_undelivered"] += len(sent) < _OBJECTS_PER_RUN
        figures["second_reports_delivered"] += max(0, len(sent) - _OBJECTS_PER_RUN)
    tally.failures += len(unrecognised) + len(partial) + sum(figures.values())
    tally.notes.update(cases=len(cases), lost_acknowledged=lost,
        duplicates_unrecognised=len(unrecognised), partial_files=len(partial), **figures,
        objects_redelivered=sum(n - 1 for c in got.values() for n in c.values()),
        partial_files_removed_at_start=sum(e.get("partial_files_removed", 0) for e in audit
                                           if e["event"] == "service_started"))
    return tally


def destination_down(root: Path, count: int) -> Tally:
    """``count`` cases measured while the OR display is down and the service is killed and
    restarted; every result must wait in the queue and arrive once the display is back."""
    tally = Tally()
    cases = [small_case("DOWN", i) for i in range(max(1, count))]
    with running_theatre(root) as theatre:
        port = theatre.display.port
        theatre.display.stop()
        client = CArmClient(theatre.port)
        for case in cases:
            for data, uid in case.views:
                tally.count(client.store(data, uid) != 0x0000, f"{uid} not acknowledged")
        client.close()
        _wait(lambda: all(c.result(theatre).is_file() for c in cases), 60.0 + 2.0 * len(cases))
        pending = theatre.root / "data" / "queue" / "pending"
        waiting = len(list(pending.glob("*.json")))
        theatre.stop_service(kill=True)
        theatre.start_service()
        theatre.display = ResultCollector(port=port)
        arrived = _wait(lambda: _all_delivered(theatre.display, cases), 60.0 + len(cases))
        _wait(lambda: not list(pending.glob("*.json")), 30.0)
        left = len(list(pending.glob("*.json"))) + len(list(pending.parent.glob("failed/*.json")))
        got = _delivered(theatre.display)
    for case in cases:
        sent = got.get(case.study_uid, Counter())
        tally.count(len(sent) != _OBJECTS_PER_RUN,
                    f"{case.patient_id}: {len(sent)} objects arrived")
    tally.failures += (waiting < _OBJECTS_PER_RUN * len(cases)) + left
    tally.notes.update(queued_while_down=waiting, all_arrived=arrived, left_in_queue=left)
    return tally


def _expose(theatre: Theatre, frame: Frame, view: int, fault: str | None,
            client: CArmClient) -> int | None:
    """Wait until the C-arm holds at ``view``, inject ``fault`` on the encoder link around the
    exposure (``stall``: the device freezes; ``line``: every byte is lost), expose, store."""
    carm = theatre.carm
    exposure = theatre.exposure_time(view, time.monotonic() + 0.6)
    time.sleep(max(0.0, exposure - _FAULT_LEAD_S - time.monotonic()))
    if fault is not None:
        # On a loaded machine the sleep can overrun past the exposure: the exposure then
        # waits for the lead after the fault began, else the last reading before the fault
        # would still be fresh at it (a faulted view initialised from the encoders).
        exposure = max(exposure, time.monotonic() + _FAULT_LEAD_S)
    if fault == "stall":
        carm.stall(2.0 * _FAULT_LEAD_S)
    elif fault == "line":
        carm.corrupt_line(FaultSpec(drop=1.0))
    time.sleep(max(0.0, exposure - time.monotonic()))
    frame.acquisition_datetime = datetime.now(UTC)
    status = client.store(dataset_bytes(frame), frame.sop_instance_uid)
    if fault == "line":
        time.sleep(max(0.0, exposure + _FAULT_LEAD_S - time.monotonic()))
        carm.corrupt_line(FaultSpec())
    return status


# A link fault begins this long before the exposure and lasts as long after it (the
# readings' freshness limit is 0.1 s).
_FAULT_LEAD_S = 0.5


SERIAL_FAULTS = ("stall", "line")


def serial_faults(root: Path, count: int) -> Tally:
    """``count`` phantom cases of three views: the first exposed with the encoder link
    healthy, the second during a link fault (so initialised from its DICOM positioner angles),
    the third during a fault and without positioner angles (so refused). The result must say
    exactly that for each view, and the encoder reading it does use must be fresh."""
    tally = Tally()
    outcomes: list[dict] = []
    with running_theatre(root, encoders=True, views_deg=(-30.0, 30.0, 0.0), hold_s=0.8,
                         move_s=1.6) as theatre:
        client = CArmClient(theatre.port)
        max_age = 0.1  # carm.max_reading_age_s of the theatre (the default)
        for i in range(max(1, count)):
            case = theatre.make_case(i)
            fault = SERIAL_FAULTS[i % len(SERIAL_FAULTS)]
            bare = replace(case.frames[2], primary_angle_deg=None, secondary_angle_deg=None)
            for view, frame, injected in ((2, bare, fault), (0, case.frames[0], None),
                                          (1, case.frames[1], fault)):
                status = _expose(theatre, frame, view, injected, client)
                tally.count(status != 0x0000, f"case {i} view {view}: status {status}")
            used = [case.frames[0].sop_instance_uid, case.frames[1].sop_instance_uid]
            path = (_data(theatre) / "output" / case_id_of(PATIENT_ID, case.study_uid, "R")
                    / run_id_of(used) / "result.json")
            if not _wait(path.is_file, 120.0):
                tally.count(True, f"case {i}: no result")
                continue
            doc = json.loads(path.read_text())
            tally.count(bool(problems := _initialisation_problems(doc, case, bare, max_age)),
                        f"case {i} ({fault}): {'; '.join(problems)}")
            outcomes.append({"fault": fault, "status": doc["status"],
                             "initialisation": [s["initialisation"] for s in doc["sources"]],
                             "ctr_error_deg": _error(doc, "ctr_deg", case.truth_ctr_deg),
                             "str_error_deg": _error(doc, "str_deg", case.truth_str_deg)})
        client.close()
    tally.notes["cases"] = outcomes
    return tally


def _error(doc: dict, name: str, truth: float) -> float | None:
    return None if doc["angles"] is None else round(doc["angles"][name] - truth, 3)


def _initialisation_problems(doc: dict, case, bare: Frame, max_age_s: float) -> list[str]:
    """What the result document gets wrong about how each view was initialised."""
    by_uid = {s["sop_instance_uid"]: s for s in doc["sources"]}
    healthy, faulted = (by_uid.get(f.sop_instance_uid, {}) for f in case.frames[:2])
    refused = by_uid.get(bare.sop_instance_uid, {})
    problems = []
    if healthy.get("initialisation") != "encoders":
        problems.append(f"healthy view initialised from {healthy.get('initialisation')}")
    else:
        reading = datetime.fromisoformat(healthy["encoder_reading"]["time_utc"])
        taken = datetime.fromisoformat(healthy["acquisition_datetime"])
        if abs((reading - taken).total_seconds()) > max_age_s:
            problems.append("the encoder reading used is not from the moment of exposure")
    if faulted.get("initialisation") != "dicom_positioner" or faulted.get("encoder_reading"):
        problems.append(f"faulted view initialised from {faulted.get('initialisation')}")
    if (refused.get("initialisation", "absent") is not None or refused.get("used")
            or not refused.get("problem")):
        problems.append("the view without geometry is not reported as refused")
    if not any("not initialised" in r for r in doc["reasons"]):
        problems.append("the reasons do not name the refused view")
    return problems


# -- soak --------------------------------------------------------------------------------

def _malformed_inputs(seed: int) -> Iterator[tuple[str, Callable[[RawAssociation], int]]]:
    """Hostile inputs in turn, each a function of a fresh association: the C-STORE status."""
    rng = np.random.default_rng(seed)
    while True:
        data, uid = small_case("SOAK-BAD", int(rng.integers(1 << 30))).views[0]
        cut = truncations(data, 40)[int(rng.integers(0, 40))]
        pixel = pixel_length_cases(data, True)[int(rng.integers(0, 7))][1]
        length = element_length_cases(data, True)[int(rng.integers(0, 6))][1]
        _, pdu, _ = next(malformed_pdus(1, int(rng.integers(1 << 30)), CARM_AE, SERVICE_AE))
        # Each input binds its own values: a consumer may hold several before calling them.
        yield "truncated", lambda a, data=data, cut=cut, uid=uid: a.store(data[:cut], uid)
        yield "path in the UID", lambda a, data=data: a.store(
            with_uid(data, "../../../../tmp/x", True), "../../../../tmp/x")
        yield "pixel data length", lambda a, pixel=pixel, uid=uid: a.store(pixel, uid)
        yield "element length", lambda a, length=length, uid=uid: a.store(length, uid)
        yield "malformed PDU", lambda a, pdu=pdu: (a.send(pdu), a.read_pdu(), 0x0000)[-1]


def _sample(proc: psutil.Process, started: float) -> dict:
    return {"t_s": round(time.monotonic() - started, 1),
            "rss_mb": round(proc.memory_info().rss / 1e6, 2), "open_fds": proc.num_fds(),
            "threads": proc.num_threads()}


def soak(root: Path, minutes: float, log: Callable[[str], None] = lambda _: None) -> Tally:
    """One frame a second (two-view cases) and one malformed input a minute for ``minutes``;
    the service's resident memory and open file descriptors every ten seconds."""
    tally, samples = Tally(), []
    malformed = _malformed_inputs(seed=3)
    kinds: Counter = Counter()
    cases: list[SmallCase] = []
    with running_theatre(root) as theatre:
        proc = psutil.Process(theatre.service.pid)
        client = CArmClient(theatre.port)
        started = time.monotonic()
        seconds = int(minutes * 60)
        for n in range(seconds):
            time.sleep(max(0.0, started + n - time.monotonic()))
            if n % 2 == 0:
                cases.append(small_case("SOAK", n // 2))
            data, uid = cases[-1].views[n % 2]
            status = client.store(data, uid)
            tally.count(status != 0x0000, f"frame {n}: status {status}")
            if n % 60 == 5:
                kind, send = next(malformed)
                kinds[kind] += 1
                tally.count(_accepted(theatre.port, send), f"malformed input ({kind}) accepted")
            if n % 10 == 0:
                samples.append(_sample(proc, started))
            if n % 300 == 0:
                log(f"soak {n // 60:4d} min  rss {samples[-1]['rss_mb']:.1f} MB  "
                    f"fds {samples[-1]['open_fds']}  failures {tally.failures}")
        client.close()
        complete = [c for c in cases if len(c.views) == 2]
        _wait(lambda: all(c.result(theatre).is_file() for c in complete), 120.0)
        samples.append(_sample(proc, started))
        alive = theatre.service.poll() is None
        missing = sum(not c.result(theatre).is_file() for c in complete)
    figures = SoakFigures.of(samples)
    tally.failures += (not alive) + missing + (figures.rss_drift_mb > MEMORY_DRIFT_LIMIT_MB) + (
        figures.fd_growth > FD_GROWTH_LIMIT)
    tally.notes.update(minutes=minutes, frames=seconds, malformed=dict(kinds),
                       cases_without_result=missing, service_alive=alive, **vars(figures),
                       samples=samples)
    return tally


def _accepted(port: int, send: Callable[[RawAssociation], int]) -> bool:
    """Whether the service acknowledged a malformed input (rather than refusing or dropping it)."""
    try:
        assoc = RawAssociation(port, calling=CARM_AE, called=SERVICE_AE, timeout_s=10.0).associate()
        status = send(assoc)
        assoc.release()
        return status < 0xA000 and status not in (0x0122, 0x0124)
    except Dropped:
        return False


@dataclass(frozen=True)
class SoakFigures:
    """Resident memory and open file descriptors of the service over a soak; drift and
    growth are measured from the first minute on (start-up allocations are not drift)."""

    rss_first_mb: float
    rss_last_mb: float
    rss_max_mb: float
    rss_drift_mb: float
    rss_slope_mb_per_hour: float
    fds_first: int
    fds_last: int
    fds_max: int
    fd_growth: int

    @staticmethod
    def of(samples: list[dict]) -> SoakFigures:
        t = np.array([s["t_s"] for s in samples])
        rss = np.array([s["rss_mb"] for s in samples])
        fds = np.array([s["open_fds"] for s in samples])
        settled = t >= min(60.0, t[-1] / 2)
        slope = np.polyfit(t[settled], rss[settled], 1)[0] * 3600 if settled.sum() >= 2 else 0.0
        first = int(np.argmax(settled))
        return SoakFigures(float(rss[first]), float(rss[-1]), float(rss.max()),
                           round(float(rss[-1] - rss[first]), 2), round(float(slope), 2),
                           int(fds[first]), int(fds[-1]), int(fds.max()),
                           int(fds[-1] - fds[first]))


def run_fault_item(name: str, root: Path, count: float) -> Tally:
    """One item by name; ``count`` is the number of stores (crash, with one kill per twenty),
    cases (destination_down, serial_faults) or minutes (soak). A failed item keeps the end of
    the service's log (the bench's folder is temporary)."""
    if name == "crash":
        tally = crash(root, int(count), max(1, int(count) // 20))
    elif name == "soak":
        tally = soak(root, count, log=lambda line: print(line, flush=True))
    else:
        items = {"destination_down": destination_down, "serial_faults": serial_faults}
        tally = items[name](root, int(count))
    service_log = root / "service.log"
    if tally.failures and service_log.is_file():
        tally.notes["service_log_tail"] = service_log.read_text(errors="replace").splitlines()[-40:]
    return tally
