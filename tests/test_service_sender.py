"""The durable send queue: C-STORE over loopback, retries with backoff, survival of restarts."""

from __future__ import annotations

import time
from pathlib import Path

from pydicom.uid import generate_uid
from service_testing import free_port, small_frame

from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.config import Destination, SenderConfig
from slamtka.service.frames import encode_frame
from slamtka.service.sender import OutgoingObject, Sender
from slamtka.sim.theatre import ResultCollector

SC = "1.2.840.10008.5.1.4.1.1.7"


def _objects(tmp_path, n=2) -> list[OutgoingObject]:
    """Secondary Capture stand-ins: XA frames re-labelled as SC (the sink accepts SC)."""
    out = []
    for k in range(n):
        ds = encode_frame(small_frame())
        ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = SC
        ds.Modality = "OT"
        path = tmp_path / f"sc-{k}.dcm"
        ds.save_as(path, enforce_file_format=True)
        out.append(OutgoingObject(path, "sc", SC, str(ds.SOPInstanceUID)))
    return out


def _sender(tmp_path, port, objects=("sr", "sc"), **config) -> tuple[Sender, AuditLog]:
    audit = AuditLog(tmp_path / "audit.jsonl")
    dest = Destination("display", "ORDISPLAY", "127.0.0.1", port, list(objects))
    settings = SenderConfig(**{"retry_initial_s": 0.2, "retry_max_s": 0.5, "max_attempts": 3,
                               "timeout_s": 5.0, **config})
    return Sender("SLAMTKA", [dest], settings, tmp_path / "queue", audit), audit


def test_results_are_delivered_by_c_store(tmp_path):
    sink = ResultCollector()
    sender, audit = _sender(tmp_path, sink.port)
    objects = _objects(tmp_path)
    try:
        sender.enqueue(objects, "case-1", "run-1")
        assert len(sender.pending()) == 2
        assert sender.run_once() == 2
        received = sink.wait(lambda ds: True, 5.0, count=2)
        assert sorted(ds.SOPInstanceUID for _, ds in received) == sorted(o.sop_instance_uid for o in objects)
        assert sender.pending() == [] and sender.failed() == []
        sent = [e for e in read_audit(audit.path) if e["event"] == "sent"]
        assert [e["destination"] for e in sent] == ["display", "display"]
    finally:
        sink.stop()
        audit.close()


def test_destination_filters_object_kinds(tmp_path):
    sender, audit = _sender(tmp_path, free_port(), objects=("sr",))
    assert sender.enqueue(_objects(tmp_path, 1), "case-1", "run-1") == []
    audit.close()


def test_a_down_destination_is_retried_with_backoff_and_survives_a_restart(tmp_path):
    port = free_port()
    # A backoff longer than a failed association takes on a loaded machine (0.2 s was not).
    sender, audit = _sender(tmp_path, port, retry_initial_s=2.0, retry_max_s=4.0)
    objects = _objects(tmp_path, 1)
    sender.enqueue(objects, "case-1", "run-1")
    assert sender.run_once() == 0
    (job,) = sender.pending()
    assert job.attempts == 1 and ("association" in job.last_error or "connect" in job.last_error)
    assert job.next_attempt > time.time()  # backing off
    assert sender.run_once() == 0 and sender.pending()[0].attempts == 1  # not due yet
    audit.close()

    # A new sender (the service restarted) finds the job on disk and delivers it.
    sink = ResultCollector(port=port)
    restarted, audit = _sender(tmp_path, port)
    try:
        assert restarted.run_once(now=time.time() + 5.0) == 1
        assert [ds.SOPInstanceUID for _, ds in sink.wait(lambda ds: True, 5.0)] == [
            objects[0].sop_instance_uid]
        events = [e["event"] for e in read_audit(audit.path)]
        assert events == ["send_failed", "sent"]
    finally:
        sink.stop()
        audit.close()


def test_after_max_attempts_a_job_is_abandoned_to_the_failed_folder(tmp_path):
    sender, audit = _sender(tmp_path, free_port(), max_attempts=2)
    sender.enqueue(_objects(tmp_path, 1), "case-1", "run-1")
    sender.run_once()
    sender.run_once(now=time.time() + 10.0)
    assert sender.pending() == [] and len(sender.failed()) == 1
    assert [e["event"] for e in read_audit(audit.path)] == ["send_failed", "send_abandoned"]
    audit.close()


def test_the_worker_thread_sends_as_soon_as_a_job_is_queued(tmp_path):
    sink = ResultCollector()
    sender, audit = _sender(tmp_path, sink.port)
    sender.start()
    try:
        sender.enqueue(_objects(tmp_path, 1), "case-1", "run-1")
        assert len(sink.wait(lambda ds: True, 10.0)) == 1
    finally:
        sender.stop()
        sink.stop()
        audit.close()


def test_a_refused_association_is_a_failure_with_the_reason(tmp_path):
    sink = ResultCollector(ae_title="ORDISPLAY")
    audit = AuditLog(tmp_path / "audit.jsonl")
    wrong_title = Destination("display", "WRONGAE", "127.0.0.1", sink.port, ["sc"])
    sender = Sender("SLAMTKA", [wrong_title], SenderConfig(timeout_s=5.0), tmp_path / "queue", audit)
    try:
        sender.enqueue(_objects(tmp_path, 1), "case-1", generate_uid())
        assert sender.run_once() == 0
        assert "association rejected" in sender.pending()[0].last_error
    finally:
        sink.stop()
        audit.close()


def test_a_closed_port_is_reported_as_connection_refused(tmp_path):
    port = free_port()
    sender, audit = _sender(tmp_path, port)
    sender.enqueue(_objects(tmp_path, 1), "case-1", "run-1")
    assert sender.run_once() == 0
    assert f"connection refused by 127.0.0.1:{port}" in sender.pending()[0].last_error
    audit.close()


def test_a_display_coming_back_gets_the_whole_queue_at_once_oldest_first(tmp_path):
    port = free_port()
    sender, audit = _sender(tmp_path, port, retry_initial_s=0.2, retry_max_s=600.0,
                            max_attempts=100)
    objects = _objects(tmp_path, 3)
    for k, obj in enumerate(objects):  # three cases, queued one after the other
        sender.enqueue([obj], f"case-{k}", "run-1")
        time.sleep(0.01)
    later = time.time()
    for _ in range(8):  # the display stays down: every job backs off to minutes
        later += 600.0
        sender.run_once(now=later)
    assert all(j.next_attempt > time.time() + 10.0 for j in sender.pending())
    sink = ResultCollector(port=port)
    try:
        assert sender.run_once() == 3  # not due, but the display answers again: all go now
        arrived = [ds.SOPInstanceUID for _, ds in sink.wait(lambda ds: True, 5.0, count=3)]
        assert arrived == [o.sop_instance_uid for o in objects]
        assert sender.pending() == []
    finally:
        sink.stop()
        audit.close()


def test_a_newer_run_of_a_case_replaces_its_undelivered_older_one(tmp_path):
    sender, audit = _sender(tmp_path, free_port())
    older, newer = _objects(tmp_path, 3)[:2], _objects(tmp_path / "..", 1)
    other = _objects(tmp_path / "..", 1)
    sender.enqueue(older, "case-1", "run-1")
    sender.enqueue(other, "case-2", "run-1")
    sender.enqueue(newer, "case-1", "run-2")
    assert sorted((j.case_id, j.run_id) for j in sender.pending()) == [
        ("case-1", "run-2"), ("case-2", "run-1")]
    superseded = [e for e in read_audit(audit.path) if e["event"] == "send_superseded"]
    assert {e["sop_instance_uid"] for e in superseded} == {o.sop_instance_uid for o in older}
    assert all(e["by_run_id"] == "run-2" for e in superseded)
    audit.close()


def test_a_damaged_job_file_is_set_aside_by_name_and_the_queue_goes_on(tmp_path):
    sender, audit = _sender(tmp_path, 9)
    pending = tmp_path / "queue" / "pending"
    (pending / "torn.json").write_text('{"id": "x", "destination": ')
    (pending / "partial.json").write_text('{"case_id": "case-1"}')
    assert sender.pending() == [] and sender.pending() == []
    damaged = sorted(p.name for p in (tmp_path / "queue" / "damaged").iterdir())
    assert damaged == ["pending-partial.json", "pending-torn.json"]
    audit.close()
    aside = [e for e in read_audit(tmp_path / "audit.jsonl") if e["event"] == "quarantined"]
    assert sorted(Path(e["file"]).name for e in aside) == ["partial.json", "torn.json"]
