"""The re-measurement loop through the real service: ``slamtka serve`` on loopback, the
simulated C-arm's encoders on a pseudo-terminal, results at a loopback OR display.

What the display learns while a case waits, a C-arm clock off the encoder stream, and an
operator's re-run and new pin set through ``slamtka case``.
"""

from __future__ import annotations

import shutil
import time

import pytest
from service_testing import run_result

from slamtka.service.audit import read_audit
from slamtka.service.cli import main
from slamtka.service.display import STATUS_SERIES
from slamtka.sim.theatre import Theatre, _evidence

pytest.importorskip("slamtka.solver.imaging.calibration")
pytestmark = pytest.mark.skipif(not shutil.which("dsrdump"), reason="DCMTK is needed")


def _notes(ds) -> dict[str, str]:
    return {i.ConceptNameCodeSequence[0].CodeValue: str(i.TextValue)
            for i in ds.ContentSequence if i.ValueType == "TEXT"}


def _statuses(th: Theatre, study_uid: str) -> list:
    return [(t, ds) for t, ds in th.display.received
            if ds.StudyInstanceUID == study_uid and ds.SeriesDescription == STATUS_SERIES]


@pytest.fixture(scope="module")
def theatre(tmp_path_factory):
    th = Theatre(tmp_path_factory.mktemp("loop"), (-30.0, 30.0), hold_s=0.8, move_s=1.6)
    th.prepare()
    th.start()
    try:
        yield th
    finally:
        th.stop()


def _events(th: Theatre, name: str) -> list[dict]:
    return [e for e in read_audit(th.root / "data" / "audit.jsonl") if e["event"] == name]


def test_a_lone_view_is_told_to_the_display_before_the_second_is_taken(theatre):
    th = theatre
    case = th.make_case(0)
    first, second = case.frames
    case.frames = [first]
    th.acquire(case)
    waited = th.display.wait(lambda ds: ds.StudyInstanceUID == case.study_uid
                             and ds.SeriesDescription == STATUS_SERIES, 30.0, count=2)
    assert {ds.Modality for _, ds in waited} == {"SR", "OT"}  # a report and a status frame
    sr = next(ds for _, ds in waited if ds.Modality == "SR")
    notes = _notes(sr)
    assert notes["SVCSTATUS"] == "Pin set 1: one view so far."
    assert notes["NEXTSTEP"] == "second view needed, at least 15 deg from the first"
    sc = next(ds for _, ds in waited if ds.Modality != "SR")
    assert sc.SeriesDescription == STATUS_SERIES and sc.BurnedInAnnotation == "YES"

    case.frames = [second]  # the second view: the measurement follows
    th.acquire(case, views=[1])
    case.frames = [first, second]
    _, result = th.wait_for_result(case, exact=True)
    assert _evidence(result) == {first.sop_instance_uid, second.sop_instance_uid}
    assert _notes(result)["MHISTORY"] == "pin set 1, measurement 1 (first view)"


def test_a_c_arm_clock_a_second_ahead_is_corrected_and_said(theatre):
    th = theatre
    case = th.make_case(1)
    th.clock_offset_s = 1.0
    try:
        th.acquire(case)
    finally:
        th.clock_offset_s = 0.0
    _, sr = th.wait_for_result(case, exact=True)
    doc = run_result(th.result_folder(case))
    assert doc["status"] == "measured", doc["reasons"]
    assert abs(doc["angles"]["ctr_deg"] - case.truth_ctr_deg) < 1.0
    assert abs(doc["angles"]["str_deg"] - case.truth_str_deg) < 1.0
    clocks = [s["clock"] for s in doc["sources"]]
    assert all(c is not None and c["status"] == "corrected" for c in clocks), clocks
    assert all(-1.5 < c["offset_s"] < -0.2 for c in clocks)  # the frames' times were ahead
    assert any("C-arm clock" in r for r in doc["reasons"])
    mismatches = [e for e in _events(th, "clock_mismatch") if e["status"] == "corrected"]
    assert {e["sop_instance_uid"] for e in mismatches} >= {f.sop_instance_uid for f in case.frames}
    # The lone first view's status said it too.
    (first_status,) = [ds for _, ds in _statuses(th, case.study_uid) if ds.Modality == "SR"]
    assert "C-arm clock" in _notes(first_status)["SVCSTATUS"]


def test_an_operator_reruns_a_case_and_starts_a_new_set(theatre, capsys):
    th = theatre
    case = th.make_case(2)
    th.acquire(case)
    _, first = th.wait_for_result(case, exact=True)
    capsys.readouterr()
    assert main(["case", "list", "--config", str(th.config)]) == 0
    listing = capsys.readouterr().out
    case_id = th.result_folder(case).parent.name
    assert case_id in listing and "patient PHANTOM-R" in listing

    assert main(["case", "rerun", case_id[:12], "--config", str(th.config), "--who", "dr a"]) == 0
    again = th.display.wait(lambda ds: ds.Modality == "SR" and ds.StudyInstanceUID == case.study_uid
                            and ds.SeriesDescription != STATUS_SERIES, 60.0, count=2)
    rerun = again[-1][1]
    assert rerun.SOPInstanceUID != first.SOPInstanceUID  # a new run, new objects
    assert _evidence(rerun) == _evidence(first)  # from the same X-rays
    assert _notes(rerun)["MHISTORY"].startswith("pin set 1, measurement 2")

    assert main(["case", "new-set", case_id, "--config", str(th.config), "--who", "dr a"]) == 0
    deadline = time.monotonic() + 10
    while not _events(th, "operator_request")[-1:] or \
            _events(th, "operator_request")[-1]["kind"] != "new-set":
        assert time.monotonic() < deadline
        time.sleep(0.1)
    capsys.readouterr()
    assert main(["case", "show", case_id, "--config", str(th.config)]) == 0
    shown = capsys.readouterr().out
    assert "measurement 2" in shown and "the next view starts a new pin set (dr a)" in shown
    requests = _events(th, "operator_request")
    assert [(e["kind"], e["who"]) for e in requests[-2:]] == [("rerun", "dr a"), ("new-set", "dr a")]
