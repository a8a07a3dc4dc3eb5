"""Faults and durability of the whole service (``slamtka serve`` as its own process), small
counts of the fault items of ``slamtka bench hardening``: forced kills, a destination that
is down, encoder-link faults at the moment of exposure, and a short soak.
"""

from __future__ import annotations

import json
import time

import psutil
import pytest
from pydicom.uid import UID

from slamtka.bench.faults import SoakFigures, crash, serial_faults, soak
from slamtka.bench.hardening import run_items
from slamtka.service.atomic_files import TEMP_PREFIX, remove_partial
from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.config import Destination, SenderConfig
from slamtka.service.pipeline import result_uid
from slamtka.service.recording import CaseRecorder
from slamtka.service.sender import OutgoingObject, Sender
from slamtka.service.spool import Spool
from slamtka.service.status import StatusBoard

pytest.importorskip("slamtka.solver.imaging.calibration",
                    reason="the C-arm calibration module (imaging) has not landed yet")
pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def test_killed_service_loses_nothing_acknowledged_and_measures_each_input_set_once(tmp_path):
    tally = crash(tmp_path, stores=12, kills=2, seed=1)
    assert tally.notes["kills"] == 2 and tally.tried == tally.notes["acknowledged"] >= 12
    assert tally.failures == 0, tally.notes
    for figure in ("lost_acknowledged", "partial_files", "cases_incomplete", "extra_results",
                   "runs_processed_twice", "second_reports_delivered", "duplicates_unrecognised"):
        assert tally.notes[figure] == 0, figure
    # per kill at most the object in flight and those of the run it cut short arrive again
    assert tally.notes["objects_redelivered"] <= 4 * tally.notes["kills"]


def test_results_wait_for_a_destination_that_is_down_across_a_restart(tmp_path):
    result = run_items(tmp_path, {"destination_down": 2})["destination_down"]
    assert result["failures"] == 0, result
    assert result["tried"] == 4 + 2  # the stores, then the cases delivered
    assert result["queued_while_down"] >= 6 and result["left_in_queue"] == 0


def test_link_faults_at_exposure_are_reported_never_used_silently(tmp_path):
    tally = serial_faults(tmp_path, 2)
    assert tally.failures == 0, tally.notes
    assert [c["fault"] for c in tally.notes["cases"]] == ["stall", "line"]
    for case in tally.notes["cases"]:
        assert case["initialisation"] == ["encoders", "dicom_positioner", None]
    doc = json.loads(next((tmp_path / "data" / "output").glob("*/*/result.json")).read_text())
    refused = [s for s in doc["sources"] if s["initialisation"] is None]
    assert refused and "no positioner angles" in refused[0]["problem"]
    # ... and each such view is audited as it arrives, before any run reports it.
    unusable = [e for e in read_audit(tmp_path / "data" / "audit.jsonl") if e["event"] == "view_unusable"]
    assert len(unusable) == 2 and all("no positioner angles" in e["reason"] for e in unusable)


def test_a_short_soak_reports_memory_and_descriptors(tmp_path):
    tally = soak(tmp_path, 0.2)
    assert tally.failures == 0, tally.notes
    assert tally.notes["malformed"] and tally.notes["service_alive"]
    assert tally.notes["rss_first_mb"] > 0 and tally.notes["fds_first"] > 0
    assert len(tally.notes["samples"]) >= 2


def test_soak_figures_measure_drift_after_the_first_minute():
    samples = [{"t_s": t, "rss_mb": 100.0 + (0.0 if t < 60 else t / 360), "open_fds": 20}
               for t in range(0, 601, 10)]
    figures = SoakFigures.of(samples)
    assert figures.rss_drift_mb == pytest.approx(600 / 360 - 60 / 360, abs=1e-6)
    assert figures.rss_slope_mb_per_hour == pytest.approx(10.0, rel=1e-6)
    assert figures.fd_growth == 0


# -- the pieces the fault items rely on, one by one ---------------------------------------

def test_what_a_killed_writer_leaves_is_removed_and_never_looks_like_an_instance(tmp_path):
    spool = Spool(tmp_path)
    (spool.instances / f"{TEMP_PREFIX}dead").write_bytes(b"\0" * 100)  # a write cut short
    assert spool.count() == 0 and spool.entries() == []
    assert remove_partial(spool.instances) == 1 and not list(spool.instances.iterdir())


def test_a_repeated_run_keeps_its_result_uids_and_its_send_jobs(tmp_path):
    assert result_uid("case-1", "run-1", "sr") == result_uid("case-1", "run-1", "sr")
    assert len({result_uid("case-1", "run-1", "sr"), result_uid("case-1", "run-2", "sr"),
                result_uid("case-1", "run-1", "view1")}) == 3
    assert UID(result_uid("case-1", "run-1", "sr")).is_valid
    dest = Destination("display", "ORDISPLAY", "127.0.0.1", 1, ["sr"])
    sender = Sender("SLAMTKA", [dest], SenderConfig(), tmp_path / "queue",
                    AuditLog(tmp_path / "audit.jsonl"))
    report = OutgoingObject(tmp_path / "sr.dcm", "sr", "1.2.840.10008.5.1.4.1.1.88.34",
                            result_uid("case-1", "run-1", "sr"))
    first = sender.enqueue([report], "case-1", "run-1")
    again = sender.enqueue([report], "case-1", "run-1")  # the run, repeated after a crash
    assert [j.id for j in first] == [j.id for j in again] and len(sender.pending()) == 1


def test_closed_recordings_free_their_threads(tmp_path):
    """A recording's writer threads end with it: ten recordings later the process has no
    more threads than after the first two (which start whatever the SDK keeps for good).
    Threads wind down asynchronously, so the count is given a moment to settle."""
    process = psutil.Process()
    for k in range(2):
        CaseRecorder(tmp_path / f"warm{k}.rrd", "case", f"warm{k}").close()
    before = process.num_threads()
    for k in range(10):
        CaseRecorder(tmp_path / f"{k}.rrd", "case", f"run{k}").close()
    deadline = time.monotonic() + 5.0
    while process.num_threads() > before and time.monotonic() < deadline:
        time.sleep(0.05)
    assert process.num_threads() <= before


def test_listing_the_queue_survives_a_job_settled_meanwhile(tmp_path):
    dest = Destination("display", "ORDISPLAY", "127.0.0.1", 1, ["sr"])
    sender = Sender("SLAMTKA", [dest], SenderConfig(), tmp_path / "queue",
                    AuditLog(tmp_path / "audit.jsonl"))
    # what the status board meets when the sender thread removes a job it has just listed
    (sender.pending_dir / "settled.json").symlink_to(tmp_path / "gone.json")
    assert sender.pending() == []


def test_a_failing_status_source_does_not_stop_the_loops(tmp_path):
    def broken() -> dict:
        raise FileNotFoundError("a job settled while it was listed")

    board = StatusBoard(tmp_path / "status.json", {"queue": broken})
    board.refresh()  # what the worker and the board's thread call: logged, not raised
    with pytest.raises(FileNotFoundError):
        board.write()
