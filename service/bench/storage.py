"""Storage robustness, counted: items of ``slamtka bench hardening`` (issue 28).

- ``enospc``: ``slamtka serve`` with its data folder on a small tmpfs (mounted by the bench,
  root only; always unmounted) that is filled to a real ENOSPC, then partly and fully freed,
  case after case. Every acknowledged store must have its ``received`` line, every case sent
  after space returned must be measured (the worker survived), the audit chain must hold and
  no partial file may be left.
- ``damaged_spool``: the service is stopped, spool files are damaged (empty or truncated
  instance, empty or corrupt sidecar), and it must start again (the port opens), each damaged
  file quarantined and audited by name.
- ``uid_conflict``: another image under a received SOP Instance UID (other pixels; other
  patient), built from real frames with the same UID, must get 0x0111 and ``uid_conflict``;
  the identical re-send stays an acknowledged duplicate.
- ``second_instance``: a second ``serve`` on the running one's data folder must exit at once
  (status 75) with a clear message, leaving the folder untouched.
- ``burst_memory``: eight associations at once store large valid frames; the receiver's peak
  resident memory growth with the ``dicom.max_frames_in_memory`` cap, against its bound and
  against the same burst uncapped.
- ``retention``: a data folder with ``count`` cases (spooled frame, results), most of them
  delivered and 40 days old, some old with a result still queued, some of today; the
  service's start-up time, ``slamtka prune``, the start-up time again. Every old delivered
  case must be gone, every queued or recent one kept, and start-up must no longer replay
  the old cases.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, replace
from pathlib import Path

from slamtka.bench.faults import CArmClient, SmallCase, running_theatre, small_case
from slamtka.bench.hardening import PeakRss, ServiceUnderTest, Tally
from slamtka.bench.hostile import RawAssociation, dataset_bytes, noise_frame
from slamtka.service.atomic_files import TEMP_PREFIX
from slamtka.service.audit import read_audit, verify_chain
from slamtka.service.decoded import MAX_BYTES
from slamtka.service.serve import EXIT_DATA_FOLDER_BUSY
from slamtka.service.spool import entry_id

__all__ = ["STORAGE_ITEMS", "run_storage_item", "small_tmpfs"]

STORAGE_ITEMS = ("enospc", "damaged_spool", "uid_conflict", "second_instance", "burst_memory",
                 "retention")
TMPFS_MB = 8
_RESULT_WAIT_S = 60.0
_DAMAGE = ("empty_instance", "truncated_instance", "empty_sidecar", "corrupt_sidecar")


def _wait(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not (ok := predicate()) and time.monotonic() < deadline:
        time.sleep(0.2)
    return ok


@contextmanager
def small_tmpfs(folder: Path, size_mb: int) -> Iterator[Path]:
    """A tmpfs of ``size_mb`` at ``folder`` (root only), unmounted whatever happens."""
    folder.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m,mode=0700", "tmpfs",
                           str(folder)], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"cannot mount a tmpfs at {folder} (needs root): {done.stderr.strip()}")
    try:
        yield folder
    finally:
        if subprocess.run(["umount", str(folder)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def _fill(path: Path, leave_bytes: int = 0) -> None:
    """Grow ``path`` until the file system is full, then give back ``leave_bytes``."""
    chunk = b"\0" * 65536
    try:
        with path.open("ab") as f:
            while True:
                f.write(chunk)
                f.flush()
    except OSError:  # full (the open itself fails when not even a directory entry fits)
        if not path.exists():
            return
    with path.open("r+b") as f:  # whatever the buffer still held did not fit
        size = f.seek(0, os.SEEK_END)
        f.truncate(max(0, size - leave_bytes))


def _store_until_accepted(client: CArmClient, case: SmallCase, attempts: int) -> list[int | None]:
    """Like a C-arm: each view again after a refusal, up to ``attempts`` times."""
    statuses = []
    for data, uid in case.views:
        for _ in range(attempts):
            status = client.store(data, uid)
            statuses.append(status)
            if status == 0x0000:
                break
            time.sleep(0.2)
    return statuses


def enospc(root: Path, count: int) -> Tally:
    """Needs root for its tmpfs; without, the item is reported skipped (nothing tried)."""
    tally = Tally()
    if os.geteuid() != 0:
        tally.notes["skipped"] = "mounting a tmpfs needs root"
        return tally
    acked: set[str] = set()
    refused = 0
    with small_tmpfs(root / "data", TMPFS_MB) as data, running_theatre(root) as theatre:
        filler = data / "filler"
        client = CArmClient(theatre.port)
        for k in range(count):
            full, half, after = (small_case(f"ENOSPC{k}", 3 * k + j) for j in range(3))
            _fill(filler)  # disk full: every store refused, nothing acknowledged unaudited
            for data_, uid in full.views:
                status = client.store(data_, uid)
                refused += status != 0x0000
                if status == 0x0000:
                    acked.add(uid)
            _fill(filler, leave_bytes=48 * 1024)  # room for a frame, not for a run's outputs
            for status, uid in zip(_store_until_accepted(client, half, 1), half.uids):
                if status == 0x0000:
                    acked.add(uid)
            _fill(filler)  # full again while the worker runs; refusals use up the audit
            for _ in range(16):  # log's last page, so the worker's own audit lines meet ENOSPC
                refused += client.store(*full.views[0]) != 0x0000
            time.sleep(2.0)
            filler.unlink()
            for case in (full, after):  # space again: the C-arm's retries and a new case
                statuses = _store_until_accepted(client, case, 5)
                acked.update(uid for uid, s in zip(case.uids, statuses[-len(case.uids):])
                             if s == 0x0000)
                measured = _wait(case.result(theatre).is_file, _RESULT_WAIT_S)
                tally.count(not measured, f"round {k}: {case.patient_id} not measured after "
                                          "space returned (worker dead?)")
            tally.count(theatre.service.poll() is not None, f"round {k}: the service exited")
        client.close()
        audit = data / "audit.jsonl"
        received = {e.get("sop_instance_uid") for e in read_audit(audit)
                    if e["event"] in ("received", "duplicate")}
        unaudited = sorted(acked - received)
        tally.count(bool(unaudited), f"acknowledged without a received line: {unaudited[:3]}")
        chain = verify_chain(audit)
        tally.count(chain.broken is not None, f"audit chain broken at line {chain.broken}")
        partial = [p.name for p in (data / "spool" / "instances").iterdir()
                   if p.name.startswith(TEMP_PREFIX)]
        tally.count(bool(partial), f"partial files: {partial[:3]}")
        tally.notes.update(tmpfs_mb=TMPFS_MB, stores_refused_while_full=refused,
                           acknowledged=len(acked), unaudited_acks=len(unaudited),
                           audit_lines=chain.lines, chain_broken_at=chain.broken,
                           worker_failures_audited=sum(e["event"] == "failed"
                                                       for e in read_audit(audit)),
                           worker_steps_survived=_log_count(root, "worker: "),
                           unauditable_failures=_log_count(root, "worker: cannot audit"))
    return tally


def _log_count(root: Path, text: str) -> int:
    """Lines of the service's log containing ``text``."""
    log = root / "service.log"
    return sum(text in line for line in log.read_text(errors="replace").splitlines())


def _damage(kind: str, instance: Path) -> Path:
    """Damage one spool entry; the file that must end in quarantine."""
    target = instance if kind.endswith("instance") else instance.with_suffix(".json")
    size = target.stat().st_size
    with target.open("r+b") as f:
        if kind.startswith("empty"):
            f.truncate(0)
        elif kind == "truncated_instance":
            f.truncate(size // 2)
        else:
            f.truncate(0)
            f.write(b'{"pairing": [unterminated')
    return target


def damaged_spool(root: Path, count: int) -> Tally:
    tally = Tally()
    with running_theatre(root, encoders=False) as theatre:
        data = root / "data"
        instances = data / "spool" / "instances"
        client = CArmClient(theatre.port)
        cases = [small_case("DAMAGED", k, angles_deg=(-30.0,)) for k in range(count + 1)]
        for case in cases:
            _store_until_accepted(client, case, 3)
        client.close()
        uids = [case.uids[0] for case in cases]
        _wait(lambda: all((instances / f"{entry_id(u)}.json").is_file() for u in uids), 30.0)
        theatre.stop_service()
        damaged = {_damage(_DAMAGE[k % len(_DAMAGE)], instances / f"{entry_id(uid)}.dcm").name:
                   _DAMAGE[k % len(_DAMAGE)] for k, uid in enumerate(uids[:-1])}  # last: intact
        try:
            theatre.start_service()
            started = True
        except RuntimeError as exc:
            started = False
            tally.notes["start_error"] = str(exc)
        tally.count(not started, "the service did not start on a damaged spool")
        audited = {e["file"]: e["reason"] for e in read_audit(data / "audit.jsonl")
                   if e["event"] == "quarantined"}
        for name, kind in damaged.items():
            moved = (data / "spool" / "quarantine" / name).exists()
            tally.count(name not in audited or not moved, f"{kind} {name} not quarantined")
        intact = instances / f"{entry_id(uids[-1])}.dcm"
        tally.count(not intact.is_file(), "the intact instance was moved")
        if started:
            client = CArmClient(theatre.port)
            fresh = small_case("DAMAGED-AFTER", 999, angles_deg=(-30.0,))
            tally.count(client.store(*fresh.views[0]) != 0x0000, "no store after the restart")
            client.close()
        tally.notes.update(damaged=sorted(damaged.values()), quarantined=len(audited),
                           reasons=sorted(set(audited.values()))[:4])
    return tally


def uid_conflict(target: ServiceUnderTest, count: int) -> Tally:
    tally = Tally()
    assoc = RawAssociation(target.port).associate()
    for k in range(count):
        first = noise_frame(1000 + k, 32)
        other_pixels = noise_frame(2000 + k, 32, first.sop_instance_uid)
        other_patient = replace(first, patient_id=f"OTHER-{k}", patient_name="Other^Patient")
        uid = first.sop_instance_uid
        tally.count(assoc.store(dataset_bytes(first), uid) != 0x0000, "first store refused")
        tally.count(assoc.store(dataset_bytes(first), uid) != 0x0000, "identical re-send refused")
        for name, frame in (("other pixels", other_pixels), ("other patient", other_patient)):
            status = assoc.store(dataset_bytes(frame), uid)
            tally.count(status != 0x0111, f"{name} under a received UID: 0x{status:04X}")
    assoc.release()
    events = [e["event"] for e in read_audit(target.audit.path)]
    conflicts, duplicates = events.count("uid_conflict"), events.count("duplicate")
    tally.count(conflicts != 2 * count or duplicates != count,
                f"audited {conflicts} conflicts, {duplicates} duplicates")
    tally.count(len(target.stored) != count, f"{len(target.stored)} queued of {count}")
    tally.notes.update(conflicts_audited=conflicts, duplicates_audited=duplicates)
    return tally


def second_instance(root: Path, count: int) -> Tally:
    tally = Tally()
    with running_theatre(root, encoders=False) as theatre:
        data = root / "data"
        sentinel = data / "spool" / "instances" / f"{TEMP_PREFIX}running-instance"
        sentinel.write_bytes(b"a temporary file of the running instance")
        audit_size = (data / "audit.jsonl").stat().st_size
        seconds = []
        for _ in range(count):
            started = time.perf_counter()
            done = subprocess.run([sys.executable, "-m", "slamtka.service.cli", "serve",
                                   "--config", str(theatre.config)],
                                  capture_output=True, text=True, timeout=120)
            seconds.append(time.perf_counter() - started)
            tally.count(done.returncode != EXIT_DATA_FOLDER_BUSY or "in use" not in done.stderr,
                        f"second serve: status {done.returncode}: {done.stderr[-200:]}")
        tally.count(not sentinel.exists(), "the running instance's temporary file was removed")
        tally.count((data / "audit.jsonl").stat().st_size != audit_size, "the audit log changed")
        client = CArmClient(theatre.port)
        probe = small_case("SECOND", 1, angles_deg=(-30.0,))
        tally.count(client.store(*probe.views[0]) != 0x0000, "the running instance stopped serving")
        client.close()
        sentinel.unlink()
        tally.notes.update(exit_status=EXIT_DATA_FOLDER_BUSY,
                           max_exit_s=round(max(seconds, default=0.0), 2))
    return tally


def _send_burst(port: int, frames: int, side: int, parallel: int, refused) -> None:
    """The C-arms' side of a burst (its own process, so that its copies of the frames are
    not counted as the receiver's): ``parallel`` associations, each refusal retried."""
    work = [(dataset_bytes(f), f.sop_instance_uid)
            for f in (noise_frame(k, side) for k in range(frames))]

    def send(indices: list[int]) -> None:
        assoc = RawAssociation(port, max_pdu=65536, timeout_s=60.0).associate()
        for i in indices:
            while assoc.store(*work[i]) == 0xA700:
                with refused.get_lock():
                    refused.value += 1
        assoc.release()

    threads = [threading.Thread(target=send, args=(list(range(t, frames, parallel)),))
               for t in range(parallel)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def _burst(root: Path, cap: int, frames: int, side: int, parallel: int) -> tuple[float, int]:
    """Peak RSS growth (MB) of a receiver while ``parallel`` associations store ``frames``
    frames of ``side`` x ``side``; the number of stores refused (and retried)."""
    target = ServiceUnderTest(root, {"max_frames_in_memory": cap, "max_associations": parallel,
                           "max_associations_per_address": parallel,
                           "max_message_bytes": 4 * side * side + (1 << 20)})
    fork = multiprocessing.get_context("fork")
    refused = fork.Value("i", 0)
    try:
        with PeakRss() as rss:
            client = fork.Process(target=_send_burst,
                                  args=(target.port, frames, side, parallel, refused))
            client.start()
            client.join()
        stored = len(target.stored)
    finally:
        target.stop()
        shutil.rmtree(root, ignore_errors=True)  # hundreds of MB of frames, often on tmpfs
    if client.exitcode != 0 or stored != frames:
        raise RuntimeError(f"burst: {stored} of {frames} frames stored (client {client.exitcode})")
    return rss.growth_mb, refused.value


_BURST_CAP = 2
_BURST_PARALLEL = 8


def burst_memory(root: Path, count: int, side: int = 2048) -> Tally:
    """``count`` frames of 8 MB (2048 x 2048, 16 bits) from eight associations at once."""
    tally = Tally()
    frame_mb = 2 * side * side / 1e6
    # Each burst in a fresh process: after a first burst the allocator keeps the freed
    # memory, and a second burst in the same process would look cheaper than it is.
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as pool:
        capped, refused = pool.submit(_burst, root / "capped", _BURST_CAP, count, side,
                                      _BURST_PARALLEL).result()
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as pool:
        uncapped, _ = pool.submit(_burst, root / "uncapped", 64, count, side,
                                  _BURST_PARALLEL).result()
    # What the configuration promises: each association may hold one message of up to
    # max_message_bytes as pynetdicom assembles it; only max_frames_in_memory of them are
    # decoded and written at once, each with up to eight copies of its frame; the decoded
    # frames kept for the worker (service.decoded), twice over for the allocator; 64 MB for
    # threads and the allocator.
    message_mb = (4 * side * side + (1 << 20)) / 1e6  # _burst's dicom.max_message_bytes
    kept_mb = max(frame_mb, min(count * frame_mb, MAX_BYTES / 1e6))
    bound = _BURST_PARALLEL * message_mb + _BURST_CAP * 8 * frame_mb + 2 * kept_mb + 64.0
    tally.count(capped > bound, f"peak growth {capped:.0f} MB over the bound {bound:.0f} MB")
    tally.notes.update(frames=count, frame_mb=round(frame_mb, 1), associations=_BURST_PARALLEL,
                       max_frames_in_memory=_BURST_CAP, rss_growth_mb=round(capped, 1),
                       bound_mb=round(bound, 1), uncapped_rss_growth_mb=round(uncapped, 1),
                       stores_refused_and_retried=refused)
    return tally


def _timed_start(theatre) -> float:
    started = time.perf_counter()
    theatre.start_service()
    return time.perf_counter() - started


def retention(root: Path, count: int) -> Tally:
    from slamtka.service.cases import case_id_of
    from slamtka.service.frames import encode_frame
    from slamtka.service.sender import SendJob
    from slamtka.service.spool import Spool

    tally = Tally()
    day = 86400.0
    with running_theatre(root, encoders=False) as theatre:
        theatre.stop_service()
        data = root / "data"
        spool, now = Spool(data / "spool"), time.time()
        kinds: dict[str, str] = {}
        for k in range(count):
            kind = "recent" if k % 10 == 0 else "queued" if k % 50 == 1 else "old"
            frame = replace(noise_frame(k, 16), patient_id=f"RETAIN-{k}", study_uid=f"1.2.826.0.1.{k}")
            case_id = case_id_of(frame.patient_id, frame.study_uid, frame.laterality)
            kinds[case_id] = kind
            entry, _ = spool.store(encode_frame(frame))
            result = data / "output" / case_id / "run-1" / "result.json"
            result.parent.mkdir(parents=True, exist_ok=True)
            result.write_text("{}")
            if kind == "queued":
                job = data / "queue" / "pending" / f"job-{k}.json"
                job.parent.mkdir(parents=True, exist_ok=True)
                held = SendJob(f"job-{k}", "or-display", str(result), "sr", "1.2.840.10008.5.1.4.1.1.88.34",
                               f"2.25.{k}", case_id, "run-1", now, next_attempt=now + 365 * day)
                job.write_text(json.dumps(asdict(held)))  # held back: due in a year
            age = 0.0 if kind == "recent" else 40 * day
            for path in (entry.path, result):
                os.utime(path, (now - age, now - age))
        before_s = _timed_start(theatre)
        theatre.stop_service()
        done = subprocess.run([sys.executable, "-m", "slamtka.service.cli", "prune", "--config",
                               str(theatre.config)], capture_output=True, text=True, timeout=600)
        tally.count(done.returncode != 0, f"prune: {done.stderr[-300:]}")
        after_s = _timed_start(theatre)
        for case_id, kind in kinds.items():
            kept = (data / "output" / case_id).is_dir()
            tally.count(kept != (kind != "old"), f"{kind} case {case_id} {'kept' if kept else 'deleted'}")
        live = len(list((data / "spool" / "instances").glob("*.dcm")))
        tally.count(live != sum(kind != "old" for kind in kinds.values()), f"{live} frames left live")
        tally.notes.update(cases=count, old_deleted=sum(not (data / "output" / c).is_dir() for c in kinds),
                           queued_kept=sum(k == "queued" for k in kinds.values()),
                           start_before_prune_s=round(before_s, 2), start_after_prune_s=round(after_s, 2),
                           prune_says=done.stdout.strip())
    return tally


def run_storage_item(name: str, root: Path, count: int) -> Tally:
    """One item by name; ``count``: rounds (enospc), damaged files, conflicting UIDs,
    second starts or frames (burst_memory). A failed whole-service item keeps the end of
    the service's log (the bench's folder is temporary)."""
    if name == "uid_conflict":
        target = ServiceUnderTest(root)
        try:
            return uid_conflict(target, count)
        finally:
            target.stop()
    items = {"enospc": enospc, "damaged_spool": damaged_spool,
             "second_instance": second_instance, "burst_memory": burst_memory,
             "retention": retention}
    tally = items[name](root, count)
    service_log = root / "service.log"
    if tally.failures and service_log.is_file():
        tally.notes["service_log_tail"] = service_log.read_text(errors="replace").splitlines()[-40:]
    return tally
