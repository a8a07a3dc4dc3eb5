"""Deployment files: the systemd unit passes systemd-analyze verify; the container is sane."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_unit_verifies_and_is_hardened(tmp_path):
    text = (DEPLOY / "slamtka.service").read_text()
    # verify checks that ExecStart's program exists: point it at this checkout's entry point.
    executable = Path(sys.executable).parent / "slamtka"
    unit = tmp_path / "slamtka.service"
    unit.write_text(text.replace("/opt/slamtka/.venv/bin/slamtka", str(executable)))
    out = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0 and out.stderr.strip() == "", out.stderr
    settings = dict(re.findall(r"^(\w+)=(.*)$", text, re.MULTILINE))
    assert settings["Type"] == "notify" and settings["User"] == "slamtka"
    for key, value in {"NoNewPrivileges": "yes", "ProtectSystem": "strict", "ProtectHome": "yes",
                       "PrivateTmp": "yes", "DevicePolicy": "closed", "CapabilityBoundingSet": "",
                       "RestrictSUIDSGID": "yes"}.items():
        assert settings.get(key) == value, key
    assert "serve --config /etc/slamtka/slamtka.toml" in settings["ExecStart"]


def test_container_runs_unprivileged_with_a_c_echo_health_check():
    lines = [line.strip() for line in (DEPLOY / "Containerfile").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    instructions = [line.split()[0] for line in lines if line.split()[0].isupper()]
    user = next(line for line in lines if line.startswith("USER "))
    assert not user.split()[1].startswith(("root", "0"))
    assert instructions.index("USER") < instructions.index("ENTRYPOINT")
    start = next(i for i, line in enumerate(lines) if line.startswith("HEALTHCHECK"))
    health = " ".join(lines[start:start + 2])  # the instruction and its continued CMD line
    assert '"status"' in health and '"--echo"' in health
    assert "EXPOSE 11112" in lines
