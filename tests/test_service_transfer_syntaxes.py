"""Compressed transfer syntaxes over loopback: DCMTK encodes, storescu sends, the SCP decodes.

A syntax the receiver still refuses (JPEG 2000 here) is audited with the syntaxes the caller
proposed and counted.
"""

from __future__ import annotations

import numpy as np
import pydicom
import pytest
from pydicom.uid import JPEG2000Lossless, JPEGLSNearLossless, RLELossless
from pynetdicom import AE
from pynetdicom.sop_class import Verification, XRayAngiographicImageStorage
from service_testing import small_frame

from slamtka.bench.hostile import wire_bytes
from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.compressed import (
    ENCODERS,
    NEAR_LOSSLESS_DEVIATION,
    compress,
    encoders_available,
    storescu,
)
from slamtka.service.config import config_from_dict
from slamtka.service.dataset_guard import DatasetError, check_dataset_bytes
from slamtka.service.frames import decode_frame, encode_frame
from slamtka.service.scp import DicomReceiver
from slamtka.service.spool import Spool
from slamtka.service.status import Metrics

pytestmark = pytest.mark.skipif(not encoders_available(), reason="DCMTK not installed")


@pytest.fixture
def scp(tmp_path):
    table = {"dicom": {"port": 0, "allowed_calling_ae_titles": ["CARM1"]},
             "carm": {"calibration": "unused.json"}}
    config = config_from_dict(table, environ={})
    audit, metrics, stored = AuditLog(tmp_path / "audit.jsonl"), Metrics(), []
    audit.listeners.append(metrics.observe)
    receiver = DicomReceiver(config.dicom, Spool(tmp_path / "spool"), audit, stored.append)
    receiver.start()
    yield receiver, stored, metrics, tmp_path
    receiver.stop()
    audit.close()


@pytest.mark.parametrize("syntax", list(ENCODERS))
def test_a_compressed_frame_sent_by_storescu_is_spooled_and_decodes_to_its_pixels(scp, syntax):
    receiver, stored, _, tmp_path = scp
    frame = small_frame()
    plain = tmp_path / "plain.dcm"
    encode_frame(frame).save_as(plain, enforce_file_format=True)
    packed = compress(plain, syntax, tmp_path / "packed.dcm")
    out = storescu(packed, receiver.port, frame.sop_class_uid, syntax)
    assert out.returncode == 0, out.stderr
    assert [e.sop_instance_uid for e in stored] == [frame.sop_instance_uid]
    spooled = receiver.spool.read(stored[0])
    assert spooled.file_meta.TransferSyntaxUID == syntax
    pixels = decode_frame(spooled).pixels.astype(int)
    tolerance = NEAR_LOSSLESS_DEVIATION if syntax == JPEGLSNearLossless else 0
    assert np.abs(pixels - frame.pixels).max() <= tolerance


def test_a_refused_syntax_is_audited_with_the_proposal_and_counted(scp):
    receiver, stored, metrics, tmp_path = scp
    ae = AE(ae_title="CARM1")
    ae.add_requested_context(Verification)
    ae.add_requested_context(XRayAngiographicImageStorage, [JPEG2000Lossless])
    assoc = ae.associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
    assert assoc.is_established and len(assoc.accepted_contexts) == 1
    assoc.release()
    refused = [e for e in read_audit(tmp_path / "audit.jsonl") if e["event"] == "context_rejected"]
    assert len(refused) == 1, refused
    assert refused[0]["contexts"] == [{"sop_class_uid": XRayAngiographicImageStorage,
                                       "transfer_syntaxes": [JPEG2000Lossless]}]
    assert refused[0]["calling_ae"] == "CARM1" and refused[0]["peer"] == "127.0.0.1"
    assert metrics.snapshot()["contexts_rejected"] == 1


def test_the_byte_guard_walks_fragments_and_refuses_every_cut_inside_them(tmp_path):
    plain = tmp_path / "plain.dcm"
    encode_frame(small_frame()).save_as(plain, enforce_file_format=True)
    data = wire_bytes(pydicom.dcmread(compress(plain, RLELossless, tmp_path / "rle.dcm")))
    check_dataset_bytes(data, True, encapsulated=True)
    with pytest.raises(DatasetError, match="undefined length"):
        check_dataset_bytes(data, True)  # compressed pixel data on an uncompressed context
    pixel = data.index(b"\xe0\x7f\x10\x00")
    for cut in range(pixel + 12, len(data), 7):  # inside the fragments or their delimiter
        with pytest.raises(DatasetError):
            check_dataset_bytes(data[:cut], True, encapsulated=True)
