"""The encoder link driver against the simulated C-arm over real pseudo-terminals."""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from slamtka.drivers.carm_sim import DEFAULT_IDENTITY, FaultSpec, MotionScript, SimulatedCArm
from slamtka.drivers.encoder_link import EncoderLink, LinkConfig
from slamtka.drivers.kinematics import JointReading
from slamtka.drivers.protocol import (
    FrameParser,
    MessageType,
    ResultCode,
    SerialFrame,
    StatusFlags,
    encode_identity,
    encode_reading,
    encode_result,
    encode_serial_frame,
)
from slamtka.drivers.reading_history import EncoderReading, ReadingHistory
from slamtka.drivers.serial_port import (
    PortBusyError,
    PortNotFoundError,
    PortPermissionError,
    ProtocolVersionError,
    WrongDeviceError,
    open_port,
)

SCRIPT = MotionScript.from_orbital((0.0, -30.0, 30.0), hold_s=0.5, move_s=2.0)


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.fixture
def sim(tmp_path):
    with SimulatedCArm(SCRIPT, port_link=tmp_path / "carm") as device:
        yield device


def expected_counts(sim: SimulatedCArm, device_time_us: int) -> np.ndarray:
    t = (device_time_us - sim.clock_offset_us) * 1e-6
    values = sim.script.values(t, sim.identity.axis_names)[0]
    return np.round(values / np.array([a.resolution for a in sim.identity.axes])).astype(int)


def counts_of(reading) -> np.ndarray:
    values = np.array(list(reading.joints.axes().values()))
    return np.round(values / 0.001).astype(int)


def test_streams_identified_readings_that_match_the_device(sim):
    with EncoderLink(sim.port) as link:
        identity = link.wait_connected(3.0)
        assert identity == DEFAULT_IDENTITY
        assert link.state.status == "connected" and "SIM-0001" in link.state.reason
        first = link.wait_reading(2.0)
        last = first
        for _ in range(20):
            last = link.wait_reading(2.0, last.sequence)
        assert last.sequence > first.sequence and last.device_time_us > first.device_time_us
        for reading in (first, last):
            assert np.array_equal(counts_of(reading), expected_counts(sim, reading.device_time_us))
        # The device clock (7000 s ahead) is mapped onto host UTC.
        assert abs((last.received_utc - last.time_utc).total_seconds()) < 0.05
        assert last.time_utc <= last.received_utc
        doc = last.to_json()
        assert doc["joints"]["units"]["orbital"] == "deg" and doc["sequence"] == last.sequence
        once = link.read_once()
        assert once.sequence > last.sequence
        status = link.request_status()
        assert status.stream_rate_hz == 100
    assert link.state.status == "stopped"


def test_lookup_by_time_and_the_maximum_age(sim):
    with EncoderLink(sim.port) as link:
        link.wait_connected(3.0)
        time.sleep(0.3)
        latest = link.latest()
        assert latest is not None and latest.age_s() <= 0.1
        # A past reading is found by its own time; a time between two readings gets the nearer.
        past = link.reading_at(latest.time_utc - timedelta(milliseconds=100))
        assert past is not None and abs((past.time_utc - latest.time_utc).total_seconds() - -0.1) < 0.006
        assert link.reading_at(past.time_utc) == past
        assert link.reading_at(latest.time_utc - timedelta(seconds=30)) is None  # before the history
        assert link.reading_at(datetime.now(UTC) + timedelta(seconds=1)) is None  # the future
        with pytest.raises(ValueError, match="timezone-aware"):
            link.reading_at(datetime.now())
        with pytest.raises(ValueError, match="never exceeded"):
            link.reading_at(datetime.now(UTC), max_age_s=0.5)
        # A frozen device: once its last reading is older than the maximum age, nothing is
        # handed out, and the link says why.
        began = sim.stall(0.5)
        while time.monotonic() < began + 0.45:
            now_utc, now = datetime.now(UTC), time.monotonic()
            fresh, at = link.latest(), link.reading_at(now_utc)
            for reading in (fresh, at):
                assert reading is None or reading.age_s(now) <= 0.1 + 1e-9
            if now > began + 0.12:
                assert fresh is None and at is None
            time.sleep(0.01)
        assert link.state.status == "silent" and "no frame" in link.state.reason
        assert link.latest(max_age_s=0.05) is None
        link.wait_reading(2.0, link.wait_reading(2.0).sequence)
        assert link.state.status == "connected"


def test_zero_corrupted_readings_accepted_and_no_clean_frame_lost():
    faults = FaultSpec(ber=3e-4, drop=5e-3, dup=5e-3, noise=0.2, seed=9)
    received = []
    with SimulatedCArm(SCRIPT, record=True) as sim:
        config = LinkConfig(rate_hz=2000, history_s=1.0)
        with EncoderLink(sim.port, config, on_reading=received.append) as link:
            link.wait_connected(5.0)
            sim.corrupt_line(faults)
            while sim.stats.faults.frames_corrupted < 2500:
                time.sleep(0.1)
            sim.stall(60.0)
            count = -1
            while count != len(received):  # drain what is still in flight
                count = len(received)
                time.sleep(0.2)
            stats = link.stats
    truth = sim.truth.table()
    index = {int(s): k for k, s in enumerate(truth["sequence"])}
    for reading in received:
        k = index[reading.sequence]
        assert reading.device_time_us == truth["device_time_us"][k]
        assert np.array_equal(counts_of(reading), truth["counts"][k])
    accepted = np.zeros(len(truth["sequence"]), bool)
    accepted[[index[r.sequence] for r in received]] = True
    clean = ~truth["corrupted"] & truth["delivered"]
    assert clean.sum() > 2000 and not np.any(clean & ~accepted)
    assert stats.parser.crc_errors > 0 and stats.parser.header_errors > 0


def test_vanishing_device_is_detected_and_reconnected_without_leaks(sim):
    states = []
    with EncoderLink(sim.port, on_state=states.append) as link:
        link.wait_connected(3.0)
        before = None
        for cycle in range(21):
            if cycle == 1:  # after one warm-up cycle
                before = (open_fds(), threading.active_count())
            last = link.wait_reading(3.0)
            link.wait_reading(3.0, last.sequence)
            mark = len(states)
            sim.vanish()
            deadline = time.monotonic() + 3.0
            while not any(s.status == "disconnected" for s in states[mark:]):
                assert time.monotonic() < deadline, "the vanished device was not noticed"
                time.sleep(0.002)
            gone = next(s for s in states[mark:] if s.status == "disconnected")
            assert "vanished" in gone.reason and gone.error is not None
            time.sleep(0.02)
            assert link.state.status == "disconnected"
            sim.reappear()
            link.wait_connected(3.0)
        link.wait_reading(3.0)
        assert (open_fds(), threading.active_count()) == before
        assert link.stats.sessions == 22
    assert threading.active_count() == before[1] - 1  # the reader thread ended


def test_port_errors_name_the_problem(tmp_path, sim):
    missing = EncoderLink(tmp_path / "nothing")
    with missing, pytest.raises(PortNotFoundError, match="does not exist"):
        missing.wait_connected(0.5)
    regular = tmp_path / "file"
    regular.write_text("not a tty")
    with pytest.raises(WrongDeviceError, match="not a serial device"):
        open_port(str(regular), 115200, 0.01)
    with EncoderLink(sim.port) as first:
        first.wait_connected(3.0)
        with EncoderLink(sim.port) as second, pytest.raises(PortBusyError, match="busy"):
            second.wait_connected(0.5)


def test_permission_denied_is_named(sim):
    device = os.path.realpath(sim.port)
    os.chmod(device, 0o600)
    if os.geteuid() != 0:
        with pytest.raises(PortPermissionError, match="permission denied"):
            open_port(device, 115200, 0.01)
        return
    # As root nothing is denied: open it from a child that dropped to an unprivileged user.
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child reports through the pipe
        try:
            os.setgid(65534)
            os.setuid(65534)
            open_port(device, 115200, 0.01)
            message = b"opened"
        except PortPermissionError as exc:
            message = str(exc).encode()
        except BaseException as exc:
            message = repr(exc).encode()
        os.write(write_end, message)
        os._exit(0)
    os.close(write_end)
    os.waitpid(pid, 0)
    answer = os.read(read_end, 4096).decode()
    os.close(read_end)
    assert answer.startswith("permission denied opening serial port") and "dialout" in answer


def test_wrong_device_and_protocol_version(tmp_path):
    config = LinkConfig(answer_timeout_s=0.1, request_attempts=2)
    with SimulatedCArm(SCRIPT, FaultSpec(garbage=True), tmp_path / "garbage") as sim:
        with EncoderLink(sim.port, config) as link, pytest.raises(WrongDeviceError, match="no valid frame"):
            link.wait_connected(0.8)
    with SimulatedCArm(SCRIPT, port_link=tmp_path / "v2", protocol_version=2) as sim:
        with EncoderLink(sim.port, config) as link:
            with pytest.raises(ProtocolVersionError,
                               match="speaks protocol version 2; this driver supports version 1"):
                link.wait_connected(0.8)
            assert link.state.status == "disconnected"


class ScriptedDevice:
    """A hand-driven device on a pty: answers the handshake, then sends what a test writes."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._answer, daemon=True)
        self._thread.start()

    def _answer(self) -> None:
        parser = FrameParser()
        while not self._stop.is_set():
            if not select.select([self.master], [], [], 0.01)[0]:
                continue
            for request in parser.feed(os.read(self.master, 4096)):
                if request.type == MessageType.IDENTIFY_REQUEST:
                    self.send(SerialFrame(MessageType.IDENTIFY, 1, 0, encode_identity(DEFAULT_IDENTITY)))
                elif request.type in (MessageType.STREAM_START, MessageType.STREAM_STOP):
                    self.send(SerialFrame(MessageType.RESULT, 2, 0,
                                    encode_result(request.type, request.sequence, ResultCode.OK)))

    def send(self, frame: SerialFrame) -> None:
        os.write(self.master, encode_serial_frame(frame))

    def reading(self, seq: int, t_us: int, orbital_deg: float, flags: int = 0, n_axes: int = 6) -> None:
        counts = np.array([round(orbital_deg * 1000), 0, 0, 200_000, 100_000, 1_000_000][:n_axes])
        self.send(SerialFrame(MessageType.READING, seq, t_us, encode_reading(flags, 0, counts)))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        os.close(self.master)
        os.close(self.slave)


def test_implausible_readings_are_rejected():
    device = ScriptedDevice()
    got = []
    try:
        with EncoderLink(device.port, on_reading=got.append) as link:
            link.wait_connected(2.0)
            t = 5_000_000
            device.reading(10, t, 1.0)  # accepted
            device.reading(11, t + 10_000, 1.3)  # 30 deg/s: accepted (device allows 60)
            device.reading(11, t + 10_000, 1.3)  # the same frame again
            device.reading(12, t + 20_000, 3.0)  # 170 deg/s: too fast
            device.reading(13, t + 30_000, 120.0)  # beyond the declared +-95 deg
            device.reading(14, t + 40_000, 1.4, flags=StatusFlags.AXIS_FAULT)  # flagged invalid
            device.reading(15, t + 50_000, 1.4, n_axes=5)  # wrong payload size
            device.reading(16, t + 60_000, 1.5, flags=StatusFlags.MOVING)  # accepted
            deadline = time.monotonic() + 2.0
            while link.stats.readings < 3 and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(0.05)
            stats = link.stats
    finally:
        device.close()
    assert [r.sequence for r in got] == [10, 11, 16]
    assert got[-1].moving and got[-1].joints.orbital_deg == pytest.approx(1.5)
    rejected = stats.rejected
    assert (rejected.rate, rejected.duplicate, rejected.range, rejected.invalid, rejected.malformed) == (1, 1, 1, 1, 1)


def test_history_is_bounded_and_configuration_is_checked():
    history = ReadingHistory(16)
    assert history.last() is None and history.nearest(0.0, 0.1) is None
    base = datetime(2024, 1, 1, tzinfo=UTC)
    for k in range(40):
        t = base + timedelta(seconds=k)
        history.append(EncoderReading(k, k, t, t, float(k), JointReading(), 0), t.timestamp())
    assert len(history) == 16 and history.last().sequence == 39
    assert history.nearest(base.timestamp(), 0.1) is None  # overwritten
    assert history.nearest(base.timestamp() + 30.05, 0.1).sequence == 30
    assert history.nearest(base.timestamp() + 30.5, 0.1) is None  # nothing within the age
    assert LinkConfig(rate_hz=100, history_s=60).history_capacity == 6000
    with pytest.raises(ValueError, match="invalid max_age_s"):
        LinkConfig(max_age_s=0)
    with pytest.raises(ValueError, match=r"link.speed: unknown key \(known: answer_timeout_s, "):
        LinkConfig.from_config({"speed": 3})
    with pytest.raises(ValueError, match="link.rate_hz: expected an integer, got 'fast'"):
        LinkConfig.from_config({"rate_hz": "fast"})
    config = LinkConfig.from_config({"rate_hz": 50, "required_axes": ["orbital"]})
    assert LinkConfig.from_config(config.to_config()) == config


def test_history_keeps_only_the_newest(sim):
    config = LinkConfig(rate_hz=100, history_s=0.2)  # 20 readings
    with EncoderLink(sim.port, config) as link:
        link.wait_connected(3.0)
        first = last = link.wait_reading(2.0)
        while last.sequence < first.sequence + 40:
            last = link.wait_reading(2.0, last.sequence)
        assert link.reading_at(first.time_utc) is None  # overwritten
        assert len(link.history) == link.history.capacity == 20

