"""The simulated C-arm (fault specification, injection, motion script), its command line and
the link benchmark."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import numpy as np
import pytest

from slamtka.drivers.carm_sim import DEFAULT_IDENTITY, FaultInjector, FaultSpec, MotionScript
from slamtka.drivers.encoder_link import EncoderLink
from slamtka.drivers.kinematics import JointReading
from slamtka.drivers.protocol import StatusFlags
from slamtka.service.cli import main

SLAMTKA = [sys.executable, "-m", "slamtka.service.cli"]


def test_fault_spec_parses_every_fault_and_rejects_nonsense():
    spec = FaultSpec.parse("ber=1e-5, drop=1e-4,dup=2e-4,noise=0.01,stall=300ms/10s,"
                           "disconnect=0.5/20,garbage,seed=7")
    assert spec == FaultSpec(1e-5, 1e-4, 2e-4, 0.01, (0.3, 10.0), (0.5, 20.0), True, 7)
    assert FaultSpec.parse("") == FaultSpec()
    for text, message in [("bitrot=1", "unknown fault 'bitrot=1'"), ("ber=2", "not a probability"),
                          ("stall=5/1", "shorter than the period"), ("drop=lots", "malformed value"),
                          ("stall=1", "malformed value"), ("garbage=maybe", "unknown fault")]:
        with pytest.raises(ValueError, match=message):
            FaultSpec.parse(text)


def test_fault_injector_hits_at_the_requested_rates_and_flags_exactly_the_hit_frames():
    frames = [bytes([k % 251]) * 50 for k in range(4000)]
    injector = FaultInjector(FaultSpec(ber=1e-3), np.random.default_rng(1))
    out, hit = injector.apply(frames)
    assert len(out) == 200_000
    expected = 8 * 200_000 * 1e-3
    assert abs(injector.counts.bits_flipped - expected) < 5 * np.sqrt(expected)
    changed = [out[50 * k:50 * k + 50] != f for k, f in enumerate(frames)]
    assert np.array_equal(hit, changed)
    drops = FaultInjector(FaultSpec(drop=0.01, dup=0.01, noise=0.05), np.random.default_rng(2))
    out, hit = drops.apply(frames)
    c = drops.counts
    for count in (c.bytes_dropped, c.bytes_duplicated):
        assert abs(count - 2000) < 5 * np.sqrt(2000)
    assert abs(c.noise_bursts - 200) < 5 * np.sqrt(200)
    noise_bytes = len(out) - 200_000 + c.bytes_dropped - c.bytes_duplicated
    assert c.noise_bursts <= noise_bytes <= 32 * c.noise_bursts
    assert 0.5 < hit.mean() < 0.8  # 1 - 0.99**100 of frames lose or double a byte
    garbage, hit = FaultInjector(FaultSpec(garbage=True), np.random.default_rng(3)).apply(frames[:10])
    assert len(garbage) == 500 and hit.all() and garbage != b"".join(frames[:10])


def test_motion_script_holds_moves_smoothly_and_respects_the_device():
    script = MotionScript.from_orbital((0.0, -30.0), hold_s=1.0, move_s=2.0)
    axes = DEFAULT_IDENTITY.axis_names
    v = script.values(np.array([0.5, 1.0, 2.0, 3.0, 3.5, 6.0]), axes)
    assert np.allclose(v[:, 0], [0.0, 0.0, -15.0, -30.0, -30.0, 0.0])  # holds, midway, loops
    assert np.allclose(v[:, 3:], [200.0, 100.0, 1000.0])
    flags = script.flags(np.array([0.1, 0.5, 2.0]))
    assert flags.tolist() == [0, StatusFlags.XRAY_ON, StatusFlags.MOVING]
    with pytest.raises(ValueError, match="maximum rate of \\['orbital'\\]"):
        MotionScript.from_orbital((0.0, 80.0), move_s=2.0).check(DEFAULT_IDENTITY)
    with pytest.raises(ValueError, match="outside the device's range"):
        MotionScript((JointReading(orbital_deg=100.0, lift_mm=200, travel_mm=100),)).check(DEFAULT_IDENTITY)


def test_motion_script_file(tmp_path):
    path = tmp_path / "script.json"
    path.write_text(json.dumps({"hold_s": 2, "move_s": 3, "views": [{"orbital": 10, "lift": 150}]}))
    script = MotionScript.load(path)
    assert script.views == (JointReading(orbital_deg=10, lift_mm=150),) and script.move_s == 3.0
    path.write_text(json.dumps({"views": [{"tilt": 1}]}))
    with pytest.raises(ValueError, match="unknown C-arm axes"):
        MotionScript.load(path)


def test_carm_sim_command_serves_the_driver(tmp_path):
    link_path = tmp_path / "carm"
    proc = subprocess.Popen([*SLAMTKA, "carm-sim", "--port-link", str(link_path), "--views", "0,20",
                             "--faults", "noise=0.05,seed=3", "--duration", "30"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        banner = proc.stdout.readline()
        assert "protocol v1" in banner and str(link_path) in banner
        with EncoderLink(link_path) as link:
            link.wait_connected(5.0)
            reading = link.wait_reading(2.0)
            assert reading.joints.orbital_deg == 0.0 and reading.joints.lift_mm == 200.0
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "simulated C-arm stopped" in out and "noise bursts" in out
    assert not link_path.exists()  # the device took its path with it


def test_carm_sim_command_rejects_bad_options(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["carm-sim", "--faults", "ber=7"])
    assert exc.value.code == 2 and "not a probability" in capsys.readouterr().err
    assert main(["carm-sim", "--faults", "disconnect=1/5", "--duration", "0.1"]) == 2
    assert "needs --port-link" in capsys.readouterr().err
    script = tmp_path / "fast.json"
    script.write_text(json.dumps({"move_s": 0.1, "views": [{"orbital": 0}, {"orbital": 60}]}))
    assert main(["carm-sim", "--script", str(script), "--duration", "0.1"]) == 2
    assert "exceeds the maximum rate" in capsys.readouterr().err


def test_link_bench_writes_its_figures(tmp_path, capsys):
    out = tmp_path / "bench"
    code = main(["bench", "link", "--out", str(out), "--corrupted-frames", "400", "--fast-rate-hz", "2000",
                 "--latency-s", "1", "--stalls", "2", "--cycles", "3"])
    doc = json.loads((out / "link.json").read_text())
    printed = capsys.readouterr().out
    figures = {f["figure"]: f for f in doc["figures"]}
    assert len(figures) == 8 and "corrupted readings accepted" in printed
    assert figures["corrupted readings accepted"]["value"] == 0
    assert doc["corruption"]["frames_corrupted"] >= 400 and doc["corruption"]["clean_frames_lost"] == 0
    assert doc["disconnects"]["failures"] == 0 and doc["stalls"]["failures"] == 0
    assert doc["latency"]["readings"] > 50
    assert code == (0 if all(f["met"] for f in doc["figures"]) else 1)
