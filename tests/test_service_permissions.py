"""Files the service writes are private whatever the umask it was started with, and no path
carries a patient identifier (issue 28, item 9)."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pynetdicom import AE
from pynetdicom.sop_class import XRayAngiographicImageStorage
from service_testing import free_port, small_frame

from slamtka.service.frames import encode_frame
from slamtka.service.plans import PlanStore
from slamtka.sim.simulate import default_camera
from slamtka.solver.imaging.calibration_file import write_calibration

PATIENT_ID = "DOE-1234567"


def test_plan_folders_name_no_patient(tmp_path):
    store = PlanStore(tmp_path)
    for side in ("left", "right"):
        folder = store.folder(PATIENT_ID, side)
        assert PATIENT_ID not in str(folder) and "1234567" not in folder.name
        assert folder.name.startswith(f"plan-{side}-")
    assert store.folder(PATIENT_ID, "left") != store.folder("DOE_1234567", "left")


def _modes(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): stat.S_IMODE(p.lstat().st_mode)
            for p in [root, *root.rglob("*")] if not p.is_symlink()}


@pytest.mark.system
def test_a_service_started_under_umask_000_writes_nothing_others_can_read(tmp_path):
    data, port = tmp_path / "data", free_port()
    write_calibration(tmp_path / "cal.json", default_camera(), None, "test")
    config = tmp_path / "slamtka.toml"
    config.write_text(f'data_dir = "{data}"\n[dicom]\nport = {port}\nbind_address = "127.0.0.1"\n'
                      f'allowed_calling_ae_titles = ["CARM"]\n[carm]\ncalibration = "{tmp_path / "cal.json"}"\n'
                      '[health]\nhttp_port = 0\n')
    log = (tmp_path / "service.log").open("w")
    service = subprocess.Popen([sys.executable, "-m", "slamtka.service.cli", "serve", "--config", str(config)],
                               stdout=log, stderr=log, preexec_fn=lambda: os.umask(0))
    try:
        status = data / "status.json"
        deadline = time.monotonic() + 60
        while not (status.is_file() and json.loads(status.read_text()).get("state") == "running"):
            assert time.monotonic() < deadline and service.poll() is None, (tmp_path / "service.log").read_text()
            time.sleep(0.2)
        ae = AE(ae_title="CARM")
        ae.add_requested_context(XRayAngiographicImageStorage)
        assoc = ae.associate("127.0.0.1", port, ae_title="SLAMTKA")
        assert assoc.is_established
        answer = assoc.send_c_store(encode_frame(small_frame(patient_id=PATIENT_ID)))
        assoc.release()
        assert answer.Status == 0x0000
        while not list((data / "spool").rglob("*.json")):  # the assembler's sidecar too
            assert time.monotonic() < deadline
            time.sleep(0.2)
    finally:
        service.terminate()
        service.wait(timeout=60)
        log.close()
    modes = _modes(data)
    assert len(modes) > 5
    loose = {path: oct(mode) for path, mode in modes.items()
             if mode & (stat.S_IRWXO | stat.S_IWGRP)}
    assert loose == {}
    assert not [path for path in modes if PATIENT_ID in path or "1234567" in path]
