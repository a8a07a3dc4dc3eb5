"""Deployment files: the systemd unit passes systemd-analyze verify; the Containerfile, parsed
into its instructions, installs from the lock and its entry point (run here) sets the umask."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tomllib
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
                       "RestrictSUIDSGID": "yes", "UMask": "0027"}.items():
        assert settings.get(key) == value, key
    assert "serve --config /etc/slamtka/slamtka.toml" in settings["ExecStart"]


def _instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Containerfile: comments dropped, continuations joined."""
    out, pending = [], ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        continued = line.endswith("\\")
        pending += line[:-1] + " " if continued else line
        if not continued:
            keyword, _, arguments = pending.partition(" ")
            out.append((keyword, arguments.strip()))
            pending = ""
    assert not pending, "the last instruction ends in a continuation"
    return out


def _names(requirements: list[str]) -> set[str]:
    """Distribution names, normalised (PEP 503), of requirement lines or specifiers."""
    return {re.sub(r"[-_.]+", "-", re.split(r"[<>=!~\[ ;]", r.strip(), maxsplit=1)[0]).lower()
            for r in requirements if r.strip() and not r.startswith("#")}


CONTAINER = _instructions((DEPLOY / "Containerfile").read_text())
KNOWN = {"FROM", "RUN", "CMD", "LABEL", "EXPOSE", "ENV", "ADD", "COPY", "ENTRYPOINT", "VOLUME",
         "USER", "WORKDIR", "ARG", "ONBUILD", "STOPSIGNAL", "HEALTHCHECK", "SHELL"}


def test_the_container_file_parses_and_runs_unprivileged_with_a_c_echo_health_check():
    keywords = [keyword for keyword, _ in CONTAINER]
    assert keywords[0] == "FROM" and set(keywords) <= KNOWN, keywords
    user = dict(CONTAINER)["USER"]
    assert not user.split(":")[0].startswith(("root", "0"))
    assert keywords.index("USER") < keywords.index("ENTRYPOINT")
    health = dict(CONTAINER)["HEALTHCHECK"]
    command = json.loads(health.split(" CMD ", 1)[1])
    assert command[1:3] == ["status", "--config"] and command[-1] == "--echo"
    assert ("EXPOSE", "11112") in CONTAINER


def test_the_container_installs_from_the_lock_which_pins_every_dependency():
    root = DEPLOY.parent
    lock = _names((root / "requirements.lock").read_text().splitlines())
    dependencies = tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"]
    assert _names(dependencies) <= lock, _names(dependencies) - lock
    copied = [i for i, (keyword, args) in enumerate(CONTAINER)
              if keyword == "COPY" and "requirements.lock" in args.split()[:-1]]
    installs = [i for i, (keyword, args) in enumerate(CONTAINER)
                if keyword == "RUN" and "pip install" in args]
    assert copied and installs and copied[0] < installs[0]
    for i in installs:
        assert re.search(r"(--constraint|-c|-r) requirements\.lock\b", CONTAINER[i][1]), CONTAINER[i]
    documented = [line for line in (DEPLOY / "OPERATIONS.md").read_text().splitlines()
                  if "pip install" in line]
    assert documented and all("--constraint requirements.lock" in line for line in documented)


def test_the_container_entry_point_sets_umask_027_and_becomes_the_service(tmp_path):
    entry = json.loads(dict(CONTAINER)["ENTRYPOINT"])
    stub = tmp_path / "slamtka"  # stands in for the service: reports its umask and arguments
    stub.write_text('#!/bin/sh\necho "$(umask) $$ $*"\n')
    stub.chmod(0o755)
    command = [part.replace("/opt/slamtka/.venv/bin/slamtka", str(stub)) for part in entry]
    shell = subprocess.Popen([*command, "--verbose"], stdout=subprocess.PIPE, text=True)
    output = shell.communicate(timeout=30)[0]
    mask, pid, arguments = output.strip().split(" ", 2)
    assert shell.returncode == 0 and mask == "0027", output
    assert int(pid) == shell.pid  # exec: the service is the container's process, gets its signals
    assert arguments == "serve --config /etc/slamtka/slamtka.toml --verbose"
