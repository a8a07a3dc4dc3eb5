"""Honest health (issue 28, item 14) and the service log's case story (item 15).

The judgement is checked on snapshots; the whole chain — a real `slamtka serve`, its HTTP
endpoint, `slamtka status` as a process, a SIGKILL — in the system tier."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from service_testing import free_port

from slamtka.drivers.encoder_link import LinkState
from slamtka.service.health import judge, prometheus_text
from slamtka.service.status import Metrics
from slamtka.service.story import LinkWatch, tell
from slamtka.sim.simulate import default_camera
from slamtka.solver.imaging.calibration_file import write_calibration

NOW = datetime(2026, 12, 5, 9, 0, tzinfo=UTC)
SLAMTKA = [sys.executable, "-m", "slamtka.service.cli"]


def _snapshot(age_s: float = 1.0, alive: bool = True, busy_s: float | None = None,
              state: str = "running") -> dict:
    worker = {"alive": alive, "max_run_s": 120.0, "busy_with": None, "busy_since": None}
    if busy_s is not None:
        worker.update(busy_with="case C1", busy_since=(NOW - timedelta(seconds=busy_s)).isoformat())
    return {"state": state, "updated": (NOW - timedelta(seconds=age_s)).isoformat(),
            "stale_after_s": 6.0, "worker": worker,
            "metrics": {"instances_received": 4, "run_seconds_median": 0.8}}


@pytest.mark.parametrize("snapshot, up, why", [
    (_snapshot(), True, "running"),
    (_snapshot(age_s=7.0), False, "not responding: last update 7 s ago"),
    (_snapshot(alive=False), False, "worker thread is not running"),
    (_snapshot(busy_s=30.0), True, "running"),
    (_snapshot(busy_s=300.0), False, "worker is stuck: busy with case C1 for 300 s"),
    (_snapshot(state="stopped"), False, "the service is stopped"),
    (None, False, "no status snapshot"),
])
def test_health_is_judged_from_freshness_state_and_the_worker(snapshot, up, why):
    health = judge(snapshot, NOW)
    assert health.up is up and why in health.reason


def test_metrics_say_down_when_the_snapshot_is_stale():
    fresh = prometheus_text({**_snapshot(), "updated": datetime.now(UTC).isoformat()})
    stale = prometheus_text(_snapshot(age_s=3600.0))
    assert "slamtka_up 1.0" in fresh and "slamtka_up 0.0" in stale
    assert "slamtka_instances_received_total 4.0" in stale
    assert "slamtka_run_seconds_median 0.8" in stale


def test_counters_continue_from_the_previous_run():
    metrics = Metrics({"instances_received": 7, "runs_measured": 2, "unknown": 5, "runs_failed": -1})
    metrics.observe({"event": "received"})
    counters = metrics.snapshot()
    assert counters["instances_received"] == 8 and counters["runs_measured"] == 2
    assert counters["runs_failed"] == 0 and "unknown" not in counters


def test_refused_runs_are_counted_per_refusal_code_and_carried_over():
    metrics = Metrics({"refusals": {"no_plan": 2, "bad": -1}})
    for code in ("no_plan", "pin_not_seen", None):
        metrics.observe({"event": "processed", "status": "measured" if code is None
                         else "not_measured", "refusal_code": code, "seconds": 0.5})
    counters = metrics.snapshot()
    assert counters["refusals"] == {"no_plan": 3, "pin_not_seen": 1}
    assert counters["runs_not_measured"] == 2 and counters["runs_measured"] == 1
    text = prometheus_text({**_snapshot(), "metrics": counters})
    assert 'slamtka_refusals_total{code="no_plan"} 3.0' in text
    assert 'slamtka_refusals_total{code="pin_not_seen"} 1.0' in text
    assert Metrics({"refusals": "damaged"}).snapshot()["refusals"] == {}


def test_each_case_step_is_one_info_line(caplog):
    caplog.set_level(logging.DEBUG, logger="slamtka.case")
    tell({"event": "received", "sop_instance_uid": "1.2.3", "calling_ae": "CARM", "peer": "10.0.0.5"})
    tell({"event": "case_triggered", "case_id": "C1", "run_id": "r1", "sop_instance_uids": ["a", "b"],
          "separation_deg": 45.0})
    tell({"event": "processed", "case_id": "C1", "run_id": "r1", "ctr_deg": 1.234, "str_deg": -2.5,
          "verdict": "within tolerance", "seconds": 0.91, "reason": None})
    tell({"event": "processed", "case_id": "C2", "run_id": "r2", "ctr_deg": None,
          "reason": "view 2: pin 2 hidden by metal"})
    tell({"event": "sent", "case_id": "C1", "run_id": "r1", "kind": "sr", "destination": "pacs"})
    tell({"event": "pin_check", "case_id": "C1"})  # not a step of the story
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.INFO, "received 1.2.3 from CARM at 10.0.0.5"),
        (logging.INFO, "case C1 run r1: triggered with 2 views 45.0 deg apart"),
        (logging.INFO, "case C1 run r1: measured CTR +1.23, STR -2.50 deg, within tolerance (0.91 s)"),
        (logging.INFO, "case C2 run r2: not measured: view 2: pin 2 hidden by metal"),
        (logging.INFO, "case C1 run r1: sr sent to pacs"),
    ]


def _state(status: str) -> LinkState:
    return LinkState(status, f"{status} for the test", NOW, time.monotonic())


def test_a_link_flap_stays_quiet_a_lasting_drop_is_a_warning(caplog):
    caplog.set_level(logging.INFO, logger="slamtka.case")
    watch = LinkWatch("/dev/ttyS9", patience_s=0.3)
    watch.on_state(_state("disconnected"))
    watch.on_state(_state("connected"))  # back within its patience: a flap
    time.sleep(0.5)
    assert caplog.records == []
    watch.on_state(_state("silent"))
    _wait_for(lambda: caplog.records, 10.0)  # its patience's timer, however late under load
    watch.on_state(_state("connected"))
    watch.close()
    assert [(r.levelno, re.sub(r"\d+ s", "N s", r.getMessage().split(":")[1].strip()))
            for r in caplog.records] == [(logging.WARNING, "down for N s (silent for the test)"),
                                         (logging.INFO, "connected again")]


# -- the whole chain, with a real service process ----------------------------------------------

def _status(config: Path, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([*SLAMTKA, "status", "--config", str(config), *flags],
                          capture_output=True, text=True, timeout=60)


def _wait_for(condition, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.1)


@pytest.mark.system
def test_a_killed_service_is_seen_down_within_seconds_and_counters_carry_over(tmp_path):
    data, http_port = tmp_path / "data", free_port()
    write_calibration(tmp_path / "cal.json", default_camera(), None, "test")
    config = tmp_path / "slamtka.toml"
    config.write_text(f'data_dir = "{data}"\n[dicom]\nport = {free_port()}\n'
                      'bind_address = "127.0.0.1"\nallowed_calling_ae_titles = ["CARM"]\n'
                      f'[carm]\ncalibration = "{tmp_path / "cal.json"}"\n'
                      f'[health]\nsnapshot_interval_s = 0.5\nhttp_port = {http_port}\n')
    data.mkdir()
    (data / "status.json").write_text(json.dumps({  # what the previous run left
        "state": "stopped", "updated": "2026-12-04T10:00:00+00:00", "metrics": {"instances_received": 7}}))
    log = (tmp_path / "service.log").open("w")  # not a pipe: nobody would drain it
    service = subprocess.Popen([*SLAMTKA, "serve", "--config", str(config)], stdout=log, stderr=log)
    try:
        _wait_for(lambda: _status(config).returncode == 0)
        url = f"http://127.0.0.1:{http_port}"
        assert urllib.request.urlopen(f"{url}/healthz", timeout=10).read() == b"running\n"
        metrics = urllib.request.urlopen(f"{url}/metrics", timeout=10).read().decode()
        assert "slamtka_up 1.0" in metrics and "slamtka_instances_received_total 7.0" in metrics

        # A reader that closes its end early (`status | head`) gets no traceback.
        reader = subprocess.Popen([*SLAMTKA, "status", "--config", str(config), "--json"],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        reader.stdout.close()
        assert reader.wait(timeout=60) == 0 and reader.stderr.read() == b""

        os.kill(service.pid, signal.SIGKILL)
        service.wait(timeout=30)
        killed = time.monotonic()
        _wait_for(lambda: _status(config).returncode == 1, timeout_s=10.0)
        assert time.monotonic() - killed < 3 * 0.5 + 2.0
        down = _status(config)
        assert "DOWN: not responding" in down.stdout
        assert "slamtka_up 0.0" in _status(config, "--metrics").stdout
        assert _status(config, "--echo").returncode == 1
    finally:
        if service.poll() is None:
            service.kill()
            service.wait(timeout=30)
        log.close()
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(f"http://127.0.0.1:{http_port}/healthz", timeout=5)
