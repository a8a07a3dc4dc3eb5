"""Each received instance is decoded once: at receipt, facts in the sidecar, frame in memory."""

from __future__ import annotations

import json
from dataclasses import fields

import numpy as np
import pytest
from pydicom.uid import generate_uid
from pynetdicom import AE
from pynetdicom.sop_class import XRayAngiographicImageStorage
from service_testing import count_decoding, small_frame

from slamtka.drivers.kinematics import CArmKinematics
from slamtka.service.audit import AuditLog
from slamtka.service.cases import CaseAssembler
from slamtka.service.config import SenderConfig, config_from_dict
from slamtka.service.decoded import DecodedFrames
from slamtka.service.frames import Frame, FrameError, FrameHeader, encode_frame
from slamtka.service.pipeline import Pipeline
from slamtka.service.plans import PlanStore
from slamtka.service.poses import ViewGeometry
from slamtka.service.scp import DicomReceiver
from slamtka.service.sender import Sender
from slamtka.service.spool import Spool
from slamtka.service.workflow import Workflow


def _geometry() -> ViewGeometry:
    return ViewGeometry(CArmKinematics(), {}, None, 0.1, 3.0)


def _receive(root, frames) -> list:
    """Store ``frames`` through the DICOM receiver (loopback); the entries handed over."""
    config = config_from_dict({"dicom": {"port": 0, "allowed_calling_ae_titles": ["CARM1"]},
                               "carm": {"calibration": "unused.json"}}, environ={})
    stored: list = []
    audit = AuditLog(root / "receiver-audit.jsonl")
    receiver = DicomReceiver(config.dicom, Spool(root / "spool"), audit, stored.append)
    receiver.start()
    try:
        client = AE(ae_title="CARM1")
        client.add_requested_context(XRayAngiographicImageStorage)
        assoc = client.associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
        assert assoc.is_established
        for frame in frames:
            assert assoc.send_c_store(encode_frame(frame)).Status == 0x0000
        assoc.release()
    finally:
        receiver.stop()
        audit.close()
    return receiver.spool, stored


class _Worker:
    """What the service's worker runs on a spool: assembler, workflow and pipeline (no plan,
    so a run is refused, but it reads every view's frame and builds the SR and SCs)."""

    def __init__(self, root, spool: Spool):
        geometry = _geometry()
        self.audit = AuditLog(root / "audit.jsonl")
        self.pipeline = Pipeline(spool, PlanStore(root / "plans"), None, geometry, root / "output")
        self.assembler = CaseAssembler(spool, geometry, 15.0, 6)
        self.workflow = Workflow(self.pipeline, Sender("SLAMTKA", [], SenderConfig(), root / "queue",
                                                       self.audit),
                                 self.audit, root, min_separation_deg=15.0, max_views=6,
                                 new_set_on_new_series=False)

    def take(self, entry) -> bool:
        case, _ = self.assembler.add(entry)
        return self.workflow.place(case, case.views[entry.sop_instance_uid])

    def run(self):
        (case,) = self.assembler.cases.values()
        return self.pipeline.run(case, case.selection(6))


def _two_views():
    study = generate_uid()
    return [small_frame(study_uid=study, primary_angle_deg=angle) for angle in (-30.0, 30.0)]


def test_an_instance_is_decoded_once_on_the_normal_path(tmp_path, monkeypatch):
    calls = count_decoding(monkeypatch)
    frames = _two_views()
    spool, stored = _receive(tmp_path, frames)
    assert calls == {"decode_frame": 2, "decode_pixels": 2}  # the receiver's, to validate
    sidecar = json.loads(stored[0].sidecar.read_text())
    assert FrameHeader.from_json(sidecar["frame"]) == frames[0].header()
    assert sidecar["instance_bytes"] == stored[0].path.stat().st_size
    worker = _Worker(tmp_path, spool)
    assert [worker.take(entry) for entry in stored] == [False, True]
    result = worker.run().result
    assert result.refusal is not None and result.refusal.code == "no_plan"
    assert len(result.sources) == 2
    assert calls == {"decode_frame": 2, "decode_pixels": 2}  # assembly, status, run: none
    assert {"frame", "pairing", "instance_bytes"} <= set(json.loads(stored[0].sidecar.read_text()))


def test_a_restart_uses_the_sidecar_and_reads_only_pixels(tmp_path, monkeypatch):
    frames = _two_views()
    _, stored = _receive(tmp_path, frames)
    first = _Worker(tmp_path, Spool(tmp_path / "spool"))
    assert [first.take(entry) for entry in stored] == [False, True]
    calls = count_decoding(monkeypatch)
    spool = Spool(tmp_path / "spool")  # the service started again
    worker = _Worker(tmp_path, spool)
    for entry in spool.entries():
        worker.assembler.add(entry)
    assert calls == {}  # the cases are rebuilt from the sidecars alone
    result = worker.run().result
    assert result.refusal is not None and result.refusal.code == "no_plan"
    assert calls == {"decode_pixels": 2}  # each frame's pixels once, its header never
    again = spool.decoded.get(spool.entry(frames[1].sop_instance_uid)).frame
    assert again.header() == frames[1].header() and np.array_equal(again.pixels, frames[1].pixels)


def test_an_instance_spooled_without_facts_is_decoded_once_and_its_sidecar_rewritten(
        tmp_path, monkeypatch):
    spool = Spool(tmp_path)
    frame = small_frame()
    entry, _ = spool.store(encode_frame(frame))
    old = _geometry().pair(frame.header()).to_json()
    spool.write_sidecar(entry, old)  # as the assembler wrote it before the facts were kept
    calls = count_decoding(monkeypatch)
    restarted = Spool(tmp_path)
    case, _ = CaseAssembler(restarted, _geometry(), 15.0, 6).add(entry)
    assert restarted.decoded.get(entry).frame.header() == frame.header()
    assert calls["decode_frame"] == 1 and calls["decode_pixels"] == 1
    sidecar = json.loads(entry.sidecar.read_text())
    assert sidecar["pairing"] == old and FrameHeader.from_json(sidecar["frame"]) == frame.header()
    assert case.views[frame.sop_instance_uid].pairing.to_json() == old


def test_facts_of_another_version_are_decoded_again(tmp_path):
    spool = Spool(tmp_path)
    frame = small_frame()
    entry, _ = spool.store(encode_frame(frame), frame.header())
    doc = json.loads(entry.sidecar.read_text())
    del doc["frame"]["modality"]
    spool.write_sidecar(entry, doc)
    facts, pairing = Spool(tmp_path).decoded.facts(entry)
    assert facts == frame.header() and pairing is None
    assert "modality" in json.loads(entry.sidecar.read_text())["frame"]


def test_a_file_truncated_since_its_receipt_is_refused_without_decoding(tmp_path):
    spool = Spool(tmp_path)
    frame = small_frame()
    entry, _ = spool.store(encode_frame(frame), frame.header())
    data = entry.path.read_bytes()
    entry.path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FrameError, match="bytes"):
        Spool(tmp_path).decoded.facts(entry)


def test_the_cache_keeps_the_most_recently_used_frames(tmp_path):
    spool = Spool(tmp_path)
    decoded = DecodedFrames(spool, max_frames=2)
    entries = []
    for k in range(3):
        frame = small_frame(instance_number=k + 1)
        entry, _ = spool.store(encode_frame(frame), frame.header())
        decoded.keep(entry, frame, encode_frame(frame))
        entries.append(entry)
        if k == 1:
            decoded.get(entries[0])  # used: the second is now the oldest
    assert decoded._cached(entries[0]) is not None and decoded._cached(entries[1]) is None


def test_results_from_the_received_header_equal_those_after_a_restart(tmp_path):
    """The header handed over in memory and the one read back from the spool build the
    same objects, byte for byte."""
    spool, stored = _receive(tmp_path, _two_views())
    worker = _Worker(tmp_path, spool)
    for entry in stored:
        worker.take(entry)
    first = worker.run()
    before = {p.name: p.read_bytes() for p in first.folder.glob("*.dcm")}
    (first.folder / "result.json").unlink()
    restarted = _Worker(tmp_path, Spool(tmp_path / "spool"))
    for entry in stored:
        restarted.assembler.add(entry)
    again = restarted.run()
    assert again.folder == first.folder and len(before) == 3
    assert {p.name: p.read_bytes() for p in again.folder.glob("*.dcm")} == before


def test_the_facts_are_every_attribute_of_a_frame_but_its_pixels():
    names = {f.name for f in fields(Frame)} - {"pixels", "bits_stored"}
    assert {f.name for f in fields(FrameHeader)} == names
    frame = small_frame()
    assert FrameHeader.from_json(json.loads(json.dumps(frame.header().to_json()))) == frame.header()
