"""Retention (issue 28, item 10): idle cases leave the live spool, old ones are deleted, an
undelivered result is never, and a nearly full disk refuses new frames before it fills."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from pynetdicom import AE
from pynetdicom.sop_class import Verification, XRayAngiographicImageStorage
from service_testing import small_frame

from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.config import RetentionConfig, config_from_dict
from slamtka.service.frames import encode_frame
from slamtka.service.retention import Retention, pending_case_ids
from slamtka.service.scp import DicomReceiver
from slamtka.service.spool import Spool
from slamtka.sim.simulate import default_camera
from slamtka.solver.imaging.calibration_file import write_calibration

DAY = 86400.0
NOW = time.time()


def _aged(path: Path, age_s: float) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        path.write_text("x")
    os.utime(path, (NOW - age_s, NOW - age_s))
    return path


def _queue_job(queue_dir: Path, case_id: str) -> None:
    _aged(queue_dir / "pending" / f"job-{case_id}.json", 40 * DAY).write_text(json.dumps({"case_id": case_id}))


def test_old_cases_are_deleted_but_never_one_with_a_result_still_to_send(tmp_path):
    data = tmp_path / "data"
    for case_id, age in (("case-old", 40 * DAY), ("case-unsent", 40 * DAY), ("case-recent", 2 * DAY)):
        _aged(data / "output" / case_id / "run1" / "result.json", age)
        _aged(data / "spool" / "archive" / case_id / "a.dcm", age)
        _aged(data / "pinsets" / f"{case_id}.json", age)
    _queue_job(data / "queue", "case-unsent")
    audit = AuditLog(data / "audit.jsonl")
    retention = Retention(RetentionConfig(keep_days=30), data, data / "output", audit.record)
    assert pending_case_ids(data / "queue") == {"case-unsent"}

    dry = retention.prune(pending_case_ids(data / "queue"), now=NOW, dry_run=True)
    assert dry.pruned == ["case-old"] and (data / "output" / "case-old").is_dir()
    sweep = retention.prune(pending_case_ids(data / "queue"), now=NOW)
    audit.close()
    assert sweep.pruned == ["case-old"] and sweep.kept_undelivered == ["case-unsent"]
    assert sweep.freed_bytes > 0
    assert not (data / "output" / "case-old").exists() and not (data / "spool" / "archive" / "case-old").exists()
    assert not (data / "pinsets" / "case-old.json").exists()
    assert (data / "output" / "case-unsent").is_dir() and (data / "output" / "case-recent").is_dir()
    assert [e["case_id"] for e in read_audit(data / "audit.jsonl") if e["event"] == "case_pruned"] == ["case-old"]


def test_a_live_case_is_never_pruned_however_old_its_results(tmp_path):
    data = tmp_path / "data"
    _aged(data / "output" / "case-live" / "run1" / "result.json", 90 * DAY)
    sweep = Retention(RetentionConfig(keep_days=30), data, data / "output").prune(set(), active={"case-live"},
                                                                                  now=NOW)
    assert sweep.pruned == [] and (data / "output" / "case-live").is_dir()


def test_idle_delivered_cases_leave_the_live_spool_with_their_sidecars(tmp_path):
    data = tmp_path / "data"
    live = data / "spool" / "instances"
    idle = [_aged(live / "a.dcm", 20 * 3600), _aged(live / "b.dcm", 13 * 3600)]
    _aged(live / "a.json", 20 * 3600)
    busy = [_aged(live / "c.dcm", 1 * 3600)]
    unsent = [_aged(live / "d.dcm", 30 * 3600)]
    retention = Retention(RetentionConfig(archive_after_hours=12), data, data / "output")
    cases = {"case-idle": idle, "case-busy": busy, "case-unsent": unsent}
    assert retention.idle_cases(cases, pending={"case-unsent"}, now=NOW) == ["case-idle"]
    retention.archive("case-idle", idle)
    assert sorted(p.name for p in (data / "spool" / "archive" / "case-idle").iterdir()) == ["a.dcm", "a.json", "b.dcm"]
    assert sorted(p.name for p in live.iterdir()) == ["c.dcm", "d.dcm"]


def test_a_nearly_full_disk_refuses_storage_associations_not_echoes(tmp_path):
    table = {"dicom": {"port": 0, "allowed_calling_ae_titles": ["CARM1"]}, "carm": {"calibration": "x.json"}}
    config = config_from_dict(table, environ={})
    assert Retention(RetentionConfig(min_free_mb=0), tmp_path, tmp_path).space_problem() is None
    floor = Retention(RetentionConfig(min_free_mb=1e9), tmp_path, tmp_path)
    assert "disk nearly full" in floor.space_problem()
    audit = AuditLog(tmp_path / "audit.jsonl")
    receiver = DicomReceiver(config.dicom, Spool(tmp_path / "spool"), audit, lambda entry: None,
                             floor.space_problem)
    receiver.start()
    try:
        ae = AE(ae_title="CARM1")
        ae.add_requested_context(XRayAngiographicImageStorage)
        ae.add_requested_context(Verification)
        assoc = ae.associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
        assert not assoc.is_established
        health = AE(ae_title=config.dicom.health_ae_title)
        health.add_requested_context(Verification)
        echo = health.associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
        assert echo.is_established
        echo.release()
    finally:
        receiver.stop()
        audit.close()
    rejected = [e for e in read_audit(tmp_path / "audit.jsonl") if e["event"] == "association_rejected"]
    assert rejected and "disk nearly full" in rejected[0]["reason"]


def test_prune_by_hand_archives_idle_cases_so_the_next_start_replays_only_recent_ones(tmp_path):
    data = tmp_path / "data"
    spool = Spool(data / "spool")
    for k in range(3):  # three cases of long ago, one of now
        entry, _ = spool.store(encode_frame(small_frame(patient_id=f"P-{k}")))
        _aged(entry.path, 2 * DAY)
    recent, _ = spool.store(encode_frame(small_frame(patient_id="P-now")))
    write_calibration(tmp_path / "cal.json", default_camera(), None, "test")
    config = tmp_path / "slamtka.toml"
    config.write_text(f'data_dir = "{data}"\n[dicom]\nallowed_calling_ae_titles = ["C"]\n'
                      f'[carm]\ncalibration = "{tmp_path / "cal.json"}"\n[retention]\narchive_after_hours = 12\n')
    prune = [sys.executable, "-m", "slamtka.service.cli", "prune", "--config", str(config)]
    dry = subprocess.run([*prune, "--dry-run"], capture_output=True, text=True, timeout=120)
    assert dry.returncode == 0 and "3 idle case(s) would be archived" in dry.stdout, dry.stderr
    assert len(spool.entries()) == 4
    done = subprocess.run(prune, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "3 idle case(s) were archived" in done.stdout, done.stderr
    assert [e.path for e in spool.entries()] == [recent.path]
    assert len(list((data / "spool" / "archive").glob("case-*/*.dcm"))) == 3
    assert sum(e["event"] == "case_archived" for e in read_audit(data / "audit.jsonl")) == 3
