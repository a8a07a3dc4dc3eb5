"""Storage robustness (issue 28): the audit log's whole lines, torn tail and hash chain;
UID conflicts, unauditable receipts and the in-memory cap at the receiver (over loopback);
the systemd watchdog; and, through the ``bench hardening`` storage items, a real ENOSPC,
a damaged spool at start-up, a second instance and a burst of large frames."""

from __future__ import annotations

import json
import os
import resource
import signal
import socket
import threading
import time
from datetime import UTC, datetime, timedelta

import pytest

from slamtka.bench.hardening import ServiceUnderTest, run_items
from slamtka.bench.hostile import RawAssociation, frame_dataset_bytes
from slamtka.service.audit import AuditLog, read_audit, verify_chain
from slamtka.service.cli import main
from slamtka.service.spool import entry_id
from slamtka.service.systemd import Watchdog, notify

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def _lines(path) -> list[bytes]:
    return path.read_bytes().splitlines()


# -- the audit log ------------------------------------------------------------------------

def test_each_line_carries_the_hash_of_the_previous_and_verify_names_the_first_broken(tmp_path, capsys):
    log = AuditLog(tmp_path / "audit.jsonl")
    for k in range(4):
        log.record("received", sop_instance_uid=f"1.2.{k}")
    log.close()
    assert main(["audit", "verify", "--data", str(tmp_path)]) == 0
    assert "4 lines, chain intact" in capsys.readouterr().out
    lines = _lines(tmp_path / "audit.jsonl")
    lines[2] = lines[2].replace(b"1.2.2", b"1.2.9")  # an edited event: line 4 no longer agrees
    (tmp_path / "audit.jsonl").write_bytes(b"\n".join(lines) + b"\n")
    assert main(["audit", "verify", "--data", str(tmp_path)]) == 1
    assert "BROKEN at line 4" in capsys.readouterr().out
    del lines[2]  # a removed event
    (tmp_path / "audit.jsonl").write_bytes(b"\n".join(lines) + b"\n")
    assert verify_chain(tmp_path / "audit.jsonl").broken == 3
    assert main(["audit", "verify", "--data", str(tmp_path / "nothing")]) == 2


def test_an_old_log_without_hashes_is_verified_from_where_the_chain_starts(tmp_path, capsys):
    path = tmp_path / "audit.jsonl"
    path.write_text("".join(json.dumps({"event": "received", "n": k}) + "\n" for k in range(3)))
    log = AuditLog(path)
    log.record("service_started")
    log.close()
    report = verify_chain(path)
    assert (report.chain_starts, report.broken, report.lines) == (4, None, 4)
    assert main(["audit", "verify", "--data", str(tmp_path)]) == 0
    assert "lines 1-3 predate the chain; it starts at line 4" in capsys.readouterr().out


def test_a_torn_tail_is_cut_at_open_and_the_repair_audited(tmp_path):
    path = tmp_path / "audit.jsonl"
    log = AuditLog(path)
    log.record("received", sop_instance_uid="1.2.3")
    log.close()
    with path.open("ab") as f:  # a power cut in the middle of the next line
        f.write(b'{"time":"2026-01-01","event":"rece')
    log = AuditLog(path)
    log.record("received", sop_instance_uid="1.2.4")
    log.close()
    events = [e["event"] for e in read_audit(path)]
    assert events == ["received", "audit_repaired", "received"]
    assert next(e for e in read_audit(path) if e["event"] == "audit_repaired")["bytes_removed"] == 34
    assert verify_chain(path).broken is None


def _record_past_a_size_limit(path, limit: int) -> None:
    """In a child process (RLIMIT_FSIZE is per process): the write crossing ``limit`` is
    short, the rest fails (EFBIG); then the limit goes and one more event is recorded."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child reports through its exit status
        try:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            log = AuditLog(path)
            soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
            try:
                log.record("received", sop_instance_uid="1.2.3.4.5.6.7.8.9" * 4)
                os._exit(3)  # a short write went unnoticed
            except OSError:
                pass
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
            log.record("received", sop_instance_uid="1.2.5")
            log.close()
            os._exit(0)
        except BaseException:
            os._exit(4)
    assert os.waitpid(pid, 0)[1] >> 8 == 0


def test_a_short_write_never_leaves_part_of_a_line(tmp_path):
    path = tmp_path / "audit.jsonl"
    log = AuditLog(path)
    log.record("service_started")
    log.close()
    _record_past_a_size_limit(path, path.stat().st_size + 20)
    lines = _lines(path)
    assert [json.loads(raw)["event"] for raw in lines] == ["service_started", "received"]
    assert json.loads(lines[1])["sop_instance_uid"] == "1.2.5"
    assert verify_chain(path).broken is None


# -- the receiver -------------------------------------------------------------------------

@pytest.fixture
def target(tmp_path):
    target = ServiceUnderTest(tmp_path, {"max_frames_in_memory": 1, "memory_wait_s": 0.0})
    yield target
    target.stop()


def _events(target: ServiceUnderTest, name: str) -> list[dict]:
    return [e for e in read_audit(target.audit.path) if e["event"] == name]


def test_another_image_under_a_received_uid_is_refused_an_identical_one_acknowledged(target):
    data, uid = frame_dataset_bytes(1, 32)
    other_pixels, same_uid = frame_dataset_bytes(2, 32, sop_instance_uid=uid)
    assert same_uid == uid and other_pixels != data
    assoc = RawAssociation(target.port).associate()
    assert assoc.store(data, uid) == 0x0000
    assert assoc.store(data, uid) == 0x0000  # the C-arm's re-send: a duplicate
    assert assoc.store(other_pixels, uid) == 0x0111
    assoc.release()
    assert [e.sop_instance_uid for e in target.stored] == [uid]
    assert len(_events(target, "duplicate")) == 1
    conflict, = _events(target, "uid_conflict")
    assert conflict["sop_instance_uid"] == uid and conflict["status"] == "0x0111"
    spooled = target.receiver.spool.read(target.receiver.spool.entry(uid))
    assert spooled.PixelData in data  # the first image is kept


def test_a_receipt_that_cannot_be_audited_is_refused_and_its_retry_queued(target):
    """ENOSPC on the audit log (``/dev/full`` behind its descriptor) after the spool write."""
    data, uid = frame_dataset_bytes(3, 32)
    saved = os.dup(target.audit._fd)
    full = os.open("/dev/full", os.O_WRONLY)
    os.dup2(full, target.audit._fd)
    try:
        assoc = RawAssociation(target.port).associate()
        assert assoc.store(data, uid) == 0xA700
    finally:
        os.dup2(saved, target.audit._fd)
        os.close(saved)
        os.close(full)
    assert not (target.root / "spool" / "instances" / f"{entry_id(uid)}.dcm").exists()
    assert assoc.store(data, uid) == 0x0000  # the C-arm's retry lands: received and queued
    assoc.release()
    assert [e.sop_instance_uid for e in target.stored] == [uid]
    assert len(_events(target, "received")) == 1 and not _events(target, "duplicate")


def test_a_store_beyond_the_frames_in_memory_cap_gets_out_of_resources(target):
    data, uid = frame_dataset_bytes(4, 32)
    assoc = RawAssociation(target.port).associate()
    assert target.receiver._in_memory.acquire(timeout=5)  # another store holds the one slot
    try:
        assert assoc.store(data, uid) == 0xA700
    finally:
        target.receiver._in_memory.release()
    assert assoc.store(data, uid) == 0x0000
    assoc.release()
    refused, = _events(target, "rejected")
    assert refused["status"] == "0xA700" and "too many frames in memory" in refused["reason"]


# -- systemd ------------------------------------------------------------------------------

def test_the_watchdog_is_pinged_only_while_the_worker_lives(tmp_path, monkeypatch):
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.settimeout(5.0)
        monkeypatch.setenv("NOTIFY_SOCKET", path)
        assert notify("READY=1") and sock.recv(64) == b"READY=1"
        alive = threading.Event()
        alive.set()
        dog = Watchdog(alive.is_set, 0.02)
        dog.start()
        assert sock.recv(64) == b"WATCHDOG=1"
        alive.clear()
        dog._thread.join(5.0)
        assert not dog._thread.is_alive()
        messages = []
        sock.settimeout(0.2)
        try:
            while True:
                messages.append(sock.recv(128))
        except TimeoutError:
            pass
        assert messages and messages[-1].startswith(b"STATUS=worker thread not alive")
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert not notify("READY=1")  # outside systemd: nothing


# -- the worker ---------------------------------------------------------------------------

@pytest.fixture
def service(tmp_path):
    """The whole service in this process (no encoders), its results going nowhere."""
    from service_testing import free_port

    from slamtka.service.config import load_config
    from slamtka.service.serve import Service
    from slamtka.sim.theatre import Theatre

    theatre = Theatre(tmp_path, encoders=False)
    theatre.prepare()
    service = Service(load_config(theatre.write_config(free_port(), "")))
    service.start()
    yield service
    if service._state != "stopped":
        service.stop()


def test_the_worker_survives_an_audit_log_it_cannot_write(service):
    """A real ENOSPC (``/dev/full`` behind the audit log's descriptor) in the middle of a
    case's run: the worker thread lives on and keeps beating; the audit log resumes."""
    from pydicom.uid import generate_uid
    from service_testing import small_frame

    from slamtka.service.frames import encode_frame

    saved = os.dup(service.audit._fd)
    full = os.open("/dev/full", os.O_WRONLY)
    try:
        study, series = generate_uid(), generate_uid()
        os.dup2(full, service.audit._fd)
        for angle in (-30.0, 30.0):  # a two-view case: due, so the worker runs and audits it
            frame = small_frame(primary_angle_deg=angle, study_uid=study, series_uid=series,
                                sop_instance_uid=generate_uid())
            entry, _ = service.spool.store(encode_frame(frame))
            service._incoming.put(entry)

        def last_beat() -> datetime:
            return datetime.fromisoformat(service._worker_status()["last_beat"])

        beat = datetime.now(UTC) + timedelta(seconds=1)
        deadline = time.monotonic() + 30.0
        while last_beat() <= beat and time.monotonic() < deadline:
            time.sleep(0.1)
        assert service._worker.is_alive() and service._worker_status()["alive"]
        assert last_beat() > beat  # still looping after the failures
    finally:
        os.dup2(saved, service.audit._fd)
        os.close(saved)
        os.close(full)
        service.stop()
    assert verify_chain(service.config.audit_log).broken is None
    assert [e["event"] for e in read_audit(service.config.audit_log)][-1] == "service_stopped"


def test_serve_exits_non_zero_when_the_worker_thread_has_ended(service):
    from slamtka.service.serve import EXIT_WORKER_DIED, supervise

    service._incoming.put(None)  # the worker ends while the service is not stopping
    assert supervise(service, threading.Event(), poll_s=0.05) == EXIT_WORKER_DIED
    assert not service.worker_alive() and service._state == "stopped"
    assert [e["event"] for e in read_audit(service.config.audit_log)][-1] == "service_stopped"


@pytest.mark.system
def test_a_second_serve_on_the_same_data_folder_is_refused_at_once(tmp_path):
    result = run_items(tmp_path, {"second_instance": 1})["second_instance"]
    assert result["failures"] == 0, result
    assert result["exit_status"] == 75


@pytest.mark.system
def test_a_damaged_spool_is_quarantined_and_the_service_starts(tmp_path):
    result = run_items(tmp_path, {"damaged_spool": 4})["damaged_spool"]
    assert result["failures"] == 0, result
    assert result["quarantined"] == 4 and len(result["damaged"]) == 4


@pytest.mark.system
@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tmpfs needs root")
def test_a_real_enospc_loses_no_acknowledged_frame_and_the_worker_measures_on(tmp_path):
    result = run_items(tmp_path, {"enospc": 1})["enospc"]
    assert result["failures"] == 0, result
    assert result["stores_refused_while_full"] > 0 and result["unaudited_acks"] == 0


def test_uid_conflicts_counted_by_the_bench(tmp_path):
    result = run_items(tmp_path, {"uid_conflict": 2})["uid_conflict"]
    assert result["failures"] == 0 and result["conflicts_audited"] == 4, result


def test_a_burst_of_large_frames_stays_within_the_memory_bound(tmp_path):
    from slamtka.bench.storage import burst_memory

    tally = burst_memory(tmp_path, 8, side=1024)
    assert tally.failures == 0, tally.notes
    assert 0 < tally.notes["rss_growth_mb"] <= tally.notes["bound_mb"]
