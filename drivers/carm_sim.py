"""The simulated C-arm: a device serving the encoder protocol on a pseudo-terminal.

To the driver it is a real serial device (``os.openpty``; the slave side is the port). The
joints follow a motion script (hold at each view, move smoothly to the next), and faults can
be injected on the line and the device:

- ``ber=P``          every transmitted bit flips with probability P
- ``drop=P``         every transmitted byte is lost with probability P
- ``dup=P``          every transmitted byte is sent twice with probability P
- ``noise=P``        before each frame, with probability P, a burst of 1-32 random bytes
- ``stall=D/E``      every E seconds the device freezes for D seconds (sends and answers nothing)
- ``disconnect=D/E`` every E seconds the device vanishes for D seconds: its path is removed
                     and its pty closed, then it returns on a fresh pty (needs --port-link)
- ``garbage``        the device answers and streams random bytes (a wrong device)
- ``seed=N``         seed of the fault generator

e.g. ``--faults ber=1e-5,drop=1e-4,noise=0.01,stall=300ms/10s,disconnect=0.5/20``.
"""

from __future__ import annotations

import argparse
import os
import queue
import select
import signal
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamtka.drivers.kinematics import JointReading
from slamtka.drivers.protocol import (
    PROTOCOL_VERSION,
    AxisInfo,
    DeviceIdentity,
    DeviceStatus,
    FrameParser,
    MessageType,
    ProtocolError,
    ResultCode,
    SerialFrame,
    StatusFlags,
    decode_stream_start,
    encode_identity,
    encode_readings,
    encode_result,
    encode_serial_frame,
    encode_status,
)
from slamtka.solver.jsonfile import read_json_object

__all__ = ["FaultSpec", "FaultInjector", "MotionScript", "SimulatedCArm", "SimStats", "TruthLog",
           "DEFAULT_IDENTITY", "add_carm_sim_parser"]

DEFAULT_IDENTITY = DeviceIdentity(
    model="SLAMTKA-SIM C-arm", serial_number="SIM-0001", firmware="sim-1.0",
    axes=(
        AxisInfo("orbital", "deg", 0.001, -95.0, 95.0, 60.0),
        AxisInfo("angulation", "deg", 0.001, -190.0, 190.0, 60.0),
        AxisInfo("wigwag", "deg", 0.001, -12.5, 12.5, 30.0),
        AxisInfo("lift", "mm", 0.001, 0.0, 450.0, 100.0),
        AxisInfo("travel", "mm", 0.001, 0.0, 200.0, 100.0),
        AxisInfo("sid", "mm", 0.001, 900.0, 1200.0, 50.0),
    ),
)
MAX_RATE_HZ = 5000
TX_BUFFER_BYTES = 16384  # the device's transmit buffer; beyond it frames are dropped (overrun)


def _duration(text: str) -> float:
    text = text.strip()
    scale = 1e-3 if text.endswith("ms") else 1.0
    value = float(text.removesuffix("ms").removesuffix("s"))
    if not value > 0:
        raise ValueError
    return value * scale


@dataclass(frozen=True)
class FaultSpec:
    ber: float = 0.0
    drop: float = 0.0
    dup: float = 0.0
    noise: float = 0.0
    stall: tuple[float, float] | None = None  # (duration, every) seconds
    disconnect: tuple[float, float] | None = None
    garbage: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("ber", "drop", "dup", "noise"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"fault {name}={value} is not a probability in [0, 1]")
        for name in ("stall", "disconnect"):
            value = getattr(self, name)
            if value is not None and not 0 < value[0] < value[1]:
                raise ValueError(f"fault {name}: the duration {value[0]} s must be positive and "
                                 f"shorter than the period {value[1]} s")

    @staticmethod
    def parse(text: str) -> FaultSpec:
        """Parse ``key=value,...`` (see the module docstring)."""
        kwargs: dict = {}
        for item in filter(None, (part.strip() for part in text.split(","))):
            key, _, value = item.partition("=")
            try:
                if key in ("ber", "drop", "dup", "noise"):
                    kwargs[key] = float(value)
                elif key in ("stall", "disconnect"):
                    duration, every = value.split("/")
                    kwargs[key] = (_duration(duration), _duration(every))
                elif key == "garbage" and value in ("", "1", "true", "yes"):
                    kwargs[key] = True
                elif key == "seed":
                    kwargs[key] = int(value)
                else:
                    raise KeyError(key)
            except KeyError:
                raise ValueError(f"unknown fault {item!r}; known: ber=P, drop=P, dup=P, noise=P, "
                                 "stall=D/E, disconnect=D/E, garbage, seed=N") from None
            except ValueError:
                raise ValueError(f"fault {item!r}: malformed value") from None
        return FaultSpec(**kwargs)


@dataclass
class FaultCounts:
    bits_flipped: int = 0
    bytes_dropped: int = 0
    bytes_duplicated: int = 0
    noise_bursts: int = 0
    frames_corrupted: int = 0


class FaultInjector:
    """Corrupts outgoing bytes as the spec says, vectorised, and says which frames it hit."""

    def __init__(self, spec: FaultSpec, rng: np.random.Generator) -> None:
        self.spec, self.rng = spec, rng
        self.counts = FaultCounts()

    def apply(self, frames: list[bytes]) -> tuple[bytes, np.ndarray]:
        """The bytes to send for ``frames`` and, per frame, whether its bytes were altered."""
        spec, rng, counts = self.spec, self.rng, self.counts
        sizes = np.fromiter(map(len, frames), dtype=np.int64, count=len(frames))
        data = np.frombuffer(b"".join(frames), dtype=np.uint8).copy()
        if spec.garbage:
            return rng.integers(0, 256, data.size, dtype=np.uint8).tobytes(), np.ones(len(frames), bool)
        touched = np.zeros(data.size, dtype=bool)
        repeats = np.ones(data.size, dtype=np.int64)
        if spec.ber:
            bits = rng.integers(0, 8 * data.size, rng.binomial(8 * data.size, spec.ber))
            np.bitwise_xor.at(data, bits // 8, (1 << (bits % 8)).astype(np.uint8))
            touched[bits // 8] = True
            counts.bits_flipped += bits.size
        if spec.drop:
            dropped = rng.random(data.size) < spec.drop
            repeats[dropped] = 0
            touched |= dropped
            counts.bytes_dropped += int(dropped.sum())
        if spec.dup:
            doubled = (rng.random(data.size) < spec.dup) & (repeats > 0)
            repeats[doubled] = 2
            touched |= doubled
            counts.bytes_duplicated += int(doubled.sum())
        out = np.repeat(data, repeats)
        owner = np.repeat(np.arange(len(frames)), sizes)
        corrupted = np.bincount(owner[touched], minlength=len(frames)) > 0
        if spec.noise:
            burst = np.flatnonzero(rng.random(len(frames)) < spec.noise)
            if burst.size:
                out_sizes = np.add.reduceat(repeats, np.r_[0, np.cumsum(sizes)[:-1]]) if data.size else sizes
                starts = np.r_[0, np.cumsum(out_sizes)[:-1]]
                lengths = rng.integers(1, 33, burst.size)
                out = np.insert(out, np.repeat(starts[burst], lengths),
                                rng.integers(0, 256, int(lengths.sum()), dtype=np.uint8))
                counts.noise_bursts += burst.size
        counts.frames_corrupted += int(corrupted.sum())
        return out.tobytes(), corrupted


@dataclass(frozen=True)
class MotionScript:
    """Hold at each view for ``hold_s``, then move to the next over ``move_s`` (cosine
    profile, so speed is continuous); after the last view return to the first."""

    views: tuple[JointReading, ...]
    hold_s: float = 3.0
    move_s: float = 2.0
    exposure_s: float = 0.2  # X-ray on for this long in the middle of each hold

    def __post_init__(self) -> None:
        if not self.views:
            raise ValueError("a motion script needs at least one view")
        if not (self.hold_s > self.exposure_s >= 0 and self.move_s > 0):
            raise ValueError("motion script: hold_s > exposure_s >= 0 and move_s > 0 are required")

    @staticmethod
    def from_orbital(angles_deg: tuple[float, ...], hold_s: float = 3.0, move_s: float = 2.0) -> MotionScript:
        """Views at these orbital angles, the C-arm otherwise at a typical knee position."""
        return MotionScript(tuple(JointReading(orbital_deg=a, lift_mm=200.0, travel_mm=100.0, sid_mm=1000.0)
                                  for a in angles_deg), hold_s, move_s)

    @staticmethod
    def load(path: Path) -> MotionScript:
        """``{"hold_s": 3, "move_s": 2, "views": [{"orbital": -30, "lift": 200, ...}, ...]}``."""
        doc = read_json_object(path)
        try:
            views = tuple(JointReading.from_axes(v) for v in doc["views"])
            return MotionScript(views, float(doc.get("hold_s", 3.0)), float(doc.get("move_s", 2.0)))
        except (KeyError, TypeError, AttributeError, ValueError) as exc:
            raise ValueError(f"motion script {path}: {exc}") from None

    def _table(self, axes: tuple[str, ...]) -> np.ndarray:
        """(views, axes) joint values; an unset SID reads the nominal 1000 mm."""
        return np.array([[v if (v := view.value(a)) is not None else 1000.0 for a in axes]
                         for view in self.views])

    def _phase(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per time: the view index, the fraction of the move to the next view (0 while
        holding) and the seconds into the current hold-and-move segment."""
        segment = self.hold_s + self.move_s
        k = (t // segment).astype(np.int64) % len(self.views)
        into = t % segment
        return k, np.clip((into - self.hold_s) / self.move_s, 0.0, 1.0), into

    def values(self, t: np.ndarray, axes: tuple[str, ...]) -> np.ndarray:
        """(len(t), len(axes)) axis values at ``t`` seconds since the device started."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        table = self._table(axes)
        k, frac, _ = self._phase(t)
        here, there = table[k], table[(k + 1) % len(self.views)]
        return here + (there - here) * (0.5 * (1.0 - np.cos(np.pi * frac)))[:, None]

    def flags(self, t: float | np.ndarray) -> np.ndarray:
        """Status flags at ``t``: MOVING between views, XRAY_ON mid-hold."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        _, _, into = self._phase(t)
        moving = (into >= self.hold_s) & (len(self.views) > 1)
        xray = ~moving & (np.abs(into - self.hold_s / 2) < self.exposure_s / 2)
        return np.where(moving, int(StatusFlags.MOVING), 0) | np.where(xray, int(StatusFlags.XRAY_ON), 0)

    def check(self, identity: DeviceIdentity) -> None:
        """Raise ValueError if a view is out of the device's range or a move too fast."""
        axes = np.array(identity.axis_names)
        table = self._table(identity.axis_names)
        lo = np.array([a.minimum for a in identity.axes])
        hi = np.array([a.maximum for a in identity.axes])
        rate = np.array([a.max_rate for a in identity.axes])
        outside = (table < lo) | (table > hi)
        if outside.any():
            k = int(np.flatnonzero(outside.any(axis=1))[0])
            raise ValueError(f"motion script view {k}: {axes[outside[k]].tolist()} outside the "
                             "device's range")
        peak = np.pi / 2 * np.abs(np.roll(table, -1, axis=0) - table) / self.move_s  # cosine profile
        if (peak > rate).any():
            k = int(np.flatnonzero((peak > rate).any(axis=1))[0])
            raise ValueError(f"motion script: the move after view {k} exceeds the maximum rate of "
                             f"{axes[peak[k] > rate].tolist()}; lengthen move_s")


class TruthLog:
    """What the simulated device streamed, for benchmarks: one row per READING frame."""

    def __init__(self, n_axes: int) -> None:
        self._rows: list[np.ndarray] = [np.zeros((0, 4 + n_axes), dtype=np.int64)]

    def add(self, seq: np.ndarray, time_us: np.ndarray, counts: np.ndarray, corrupted: np.ndarray,
            delivered: bool) -> None:
        rows = np.column_stack([seq, time_us, corrupted.astype(np.int64),
                                np.full(len(seq), int(delivered)), counts])
        self._rows.append(rows)

    def table(self) -> dict[str, np.ndarray]:
        rows = np.concatenate(self._rows)
        return {"sequence": rows[:, 0], "device_time_us": rows[:, 1], "corrupted": rows[:, 2].astype(bool),
                "delivered": rows[:, 3].astype(bool), "counts": rows[:, 4:]}


@dataclass
class SimStats:
    frames_sent: int = 0
    readings_sent: int = 0
    requests: int = 0
    overruns: int = 0  # frames dropped because the transmit buffer was full
    vanishes: int = 0
    stalls: int = 0
    faults: FaultCounts = field(default_factory=FaultCounts)


class SimulatedCArm:
    """A simulated C-arm encoder device on a pseudo-terminal, run by its own thread."""

    def __init__(self, script: MotionScript | None = None, faults: FaultSpec = FaultSpec(),
                 port_link: Path | None = None, identity: DeviceIdentity = DEFAULT_IDENTITY,
                 protocol_version: int = PROTOCOL_VERSION, record: bool = False,
                 clock_offset_us: int = 7_000_000_000) -> None:
        if faults.disconnect is not None and port_link is None:
            raise ValueError("the disconnect fault needs --port-link: the device must come back at a "
                             "path that does not change")
        self.script = script or MotionScript.from_orbital((0.0, -30.0, 30.0))
        self.script.check(identity)
        self.faults = faults
        self.port_link = None if port_link is None else Path(port_link)
        self.identity = identity
        self.version = protocol_version
        self.clock_offset_us = clock_offset_us  # the device clock is not the host's
        self.truth = TruthLog(len(identity.axes)) if record else None
        self._counts_scale = np.array([a.resolution for a in identity.axes])
        self._injector = FaultInjector(faults, np.random.default_rng(faults.seed))
        self.stats = SimStats(faults=self._injector.counts)
        self.boot_monotonic = time.monotonic()
        self.last_reading_monotonic = 0.0  # when the last READING left the device
        self._commands: queue.SimpleQueue = queue.SimpleQueue()
        self._wake_r, self._wake_w = -1, -1
        self._master = self._slave = -1
        self._pty_name = ""
        self._thread: threading.Thread | None = None
        self._parser = FrameParser()
        self._seq = 0
        self._rate = 0
        self._next_due = 0.0
        self._stalled_until = 0.0
        self._absent_until: float | None = None
        self._tx = bytearray()

    # -- control (any thread) ---------------------------------------------------------------
    @property
    def port(self) -> str:
        """The path a driver opens: the link if there is one, else the pty's name."""
        return str(self.port_link) if self.port_link is not None else self._pty_name

    @property
    def pty_name(self) -> str:
        return self._pty_name

    @property
    def present(self) -> bool:
        return self._master >= 0

    def device_time_us(self, monotonic: float) -> int:
        return int(round((monotonic - self.boot_monotonic) * 1e6)) + self.clock_offset_us

    def start(self) -> SimulatedCArm:
        self._wake_r, self._wake_w = os.pipe()
        self._open_pty()
        self._thread = threading.Thread(target=self._run, name="carm-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._thread is None:
            return
        self._call("stop")
        self._thread.join(5.0)
        self._thread = None
        os.close(self._wake_r)
        os.close(self._wake_w)

    def __enter__(self) -> SimulatedCArm:
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.stop()

    def vanish(self) -> float:
        """Remove the device path and close the pty (a pulled USB adapter); returns when."""
        return self._call("vanish")

    def reappear(self) -> float:
        """Bring the device back on a fresh pty at the same link; returns when."""
        return self._call("reappear")

    def stall(self, seconds: float) -> float:
        """Freeze the device for ``seconds`` from now; returns when the stall began."""
        return self._call("stall", seconds)

    def corrupt_line(self, spec: FaultSpec) -> float:
        """From now on, corrupt the line as ``spec`` says (its ber, drop, dup, noise and
        garbage; the stall and disconnect schedules stay as started); returns when."""
        return self._call("line", spec)

    def _call(self, command: str, arg: float | FaultSpec = 0.0) -> float:
        done = threading.Event()
        box: list = []
        self._commands.put((command, arg, done, box))
        os.write(self._wake_w, b"x")
        if not done.wait(5.0):
            raise RuntimeError(f"the simulated C-arm did not execute {command!r}")
        if isinstance(box[0], Exception):
            raise box[0]
        return box[0]

    # -- the pty ----------------------------------------------------------------------------
    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave, self._pty_name = master, slave, os.ttyname(slave)
        if self.port_link is not None:
            tmp = self.port_link.with_name(f".{self.port_link.name}.{os.getpid()}.tmp")
            tmp.unlink(missing_ok=True)
            os.symlink(self._pty_name, tmp)
            os.replace(tmp, self.port_link)
        self._parser.reset()
        self._tx.clear()
        self._rate = 0  # a device that comes back has to be asked to stream again

    def _close_pty(self) -> None:
        if self._master < 0:
            return
        if self.port_link is not None:
            self.port_link.unlink(missing_ok=True)
        os.close(self._master)
        os.close(self._slave)
        self._master = self._slave = -1

    # -- the device loop --------------------------------------------------------------------
    def _run(self) -> None:
        stall, disconnect = self.faults.stall, self.faults.disconnect
        next_stall = self.boot_monotonic + stall[1] if stall else None
        next_disconnect = self.boot_monotonic + disconnect[1] if disconnect else None
        try:
            while True:
                now = time.monotonic()
                if stall and next_stall is not None and now >= next_stall:
                    self._stall(now, stall[0])
                    next_stall += stall[1]
                if disconnect and next_disconnect is not None and now >= next_disconnect and self.present:
                    self._close_pty()
                    self.stats.vanishes += 1
                    self._absent_until = now + disconnect[0]
                    next_disconnect += disconnect[1]
                if self._absent_until is not None and now >= self._absent_until and not self.present:
                    self._open_pty()
                    self._absent_until = None
                scheduled = [t for t in (next_stall, next_disconnect, self._absent_until) if t is not None]
                if not self._serve(now, min(scheduled, default=now + 1.0)):
                    return
        finally:
            self._close_pty()

    def _serve(self, now: float, next_event: float) -> bool:
        """One wait-and-act step, waking by ``next_event`` at the latest; False once told to stop."""
        streaming = self._rate and self.present and now >= self._stalled_until
        wait = max(0.0, min(0.05, next_event - now))
        if streaming:
            due = max(0.0, self._next_due - now)
            if self._rate > 1000:
                due = max(due, 0.001)  # batch fast streams instead of spinning
            wait = min(wait, due)
        elif now < self._stalled_until:
            wait = min(wait, self._stalled_until - now)
        readable = [self._wake_r] + ([self._master] if self.present else [])
        writable = [self._master] if self.present and self._tx else []
        ready_r, _, _ = select.select(readable, writable, [], wait)
        if self._wake_r in ready_r and not self._run_commands():
            return False
        now = time.monotonic()
        frozen = now < self._stalled_until
        if self.present and self._master in ready_r:
            try:
                data = os.read(self._master, 4096)
            except (BlockingIOError, OSError):
                data = b""
            if not frozen:
                for frame in self._parser.feed(data):
                    self._answer(frame, now)
        if self.present and self._rate and not frozen:
            self._stream(now)
        if self.present and self._tx:
            self._flush()
        return True

    def _run_commands(self) -> bool:
        os.read(self._wake_r, 4096)
        keep_running = True
        while not self._commands.empty():
            command, arg, done, box = self._commands.get()
            try:
                if command == "stop":
                    keep_running = False
                elif command == "vanish":
                    self._close_pty()
                    self.stats.vanishes += 1
                elif command == "reappear":
                    if self.present:
                        raise RuntimeError("the simulated C-arm is already present")
                    self._open_pty()
                elif command == "stall":
                    self._stall(time.monotonic(), arg)
                elif command == "line":
                    self._injector.spec = arg
                box.append(time.monotonic())
            except Exception as exc:  # handed back to the caller
                box.append(exc)
            done.set()
        return keep_running

    def _stall(self, now: float, seconds: float) -> None:
        self._stalled_until = now + seconds
        self._next_due = self._stalled_until  # a frozen device samples nothing meanwhile
        self.stats.stalls += 1

    def _frame(self, mtype: MessageType, payload: bytes, at: float) -> bytes:
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        return encode_serial_frame(SerialFrame(mtype, self._seq, self.device_time_us(at), payload, self.version))

    def _readings(self, times: np.ndarray) -> tuple[list[bytes], np.ndarray]:
        """READING payloads and encoder counts for the joints at these host times."""
        t = times - self.boot_monotonic
        values = self.script.values(t, self.identity.axis_names)
        counts = np.round(values / self._counts_scale).astype(np.int64)
        return encode_readings(self.script.flags(t), np.zeros(len(t)), counts), counts

    def _answer(self, request: SerialFrame, now: float) -> None:
        self.stats.requests += 1
        mtype, result = request.type, None
        if request.version != self.version:
            result = ResultCode.VERSION_MISMATCH
        elif mtype == MessageType.IDENTIFY_REQUEST:
            self._send([self._frame(MessageType.IDENTIFY, encode_identity(self.identity), now)])
        elif mtype == MessageType.READ_ONCE:
            self._send_readings(np.array([now]))
        elif mtype == MessageType.STREAM_START:
            try:
                rate = decode_stream_start(request.payload)
                result = ResultCode.OK if 1 <= rate <= MAX_RATE_HZ else ResultCode.RATE_OUT_OF_RANGE
            except ProtocolError:
                result = ResultCode.MALFORMED
            if result == ResultCode.OK:
                self._rate, self._next_due = rate, now
        elif mtype == MessageType.STREAM_STOP:
            self._rate, result = 0, ResultCode.OK
        elif mtype == MessageType.STATUS_REQUEST:
            flags = int(self.script.flags(now - self.boot_monotonic)[0])
            status = DeviceStatus(flags, 0, self._rate, self.stats.overruns)
            self._send([self._frame(MessageType.STATUS, encode_status(status), now)])
        else:
            result = ResultCode.UNSUPPORTED
        if result is not None:
            self._send([self._frame(MessageType.RESULT, encode_result(mtype, request.sequence, result), now)])

    def _stream(self, now: float) -> None:
        period = 1.0 / self._rate
        if now - self._next_due > 1.0:  # fell far behind (host stopped reading): skip ahead
            self._next_due = now
        if self._next_due > now:
            return
        due = self._next_due + period * np.arange(int((now - self._next_due) // period) + 1)
        self._next_due = float(due[-1]) + period
        self._send_readings(due)

    def _send_readings(self, times: np.ndarray) -> None:
        payloads, counts = self._readings(times)
        frames = [self._frame(MessageType.READING, p, t) for p, t in zip(payloads, times.tolist())]
        first_seq = (self._seq - len(frames) + 1) & 0xFFFFFFFF
        corrupted, delivered = self._send(frames)
        self.stats.readings_sent += len(frames)
        self.last_reading_monotonic = time.monotonic()
        if self.truth is not None:
            self.truth.add(first_seq + np.arange(len(frames)),
                           np.array([self.device_time_us(t) for t in times.tolist()]), counts,
                           corrupted, delivered)

    def _send(self, frames: list[bytes]) -> tuple[np.ndarray, bool]:
        """Queue frames through the fault injector; (corrupted per frame, whether queued)."""
        data, corrupted = self._injector.apply(frames)
        if len(self._tx) + len(data) > TX_BUFFER_BYTES:
            self.stats.overruns += len(frames)
            return corrupted, False
        self._tx += data
        self.stats.frames_sent += len(frames)
        self._flush()
        return corrupted, True

    def _flush(self) -> None:
        try:
            written = os.write(self._master, self._tx)
        except BlockingIOError:
            return
        del self._tx[:written]


# -- command line ------------------------------------------------------------------------------


def _angles(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated angles, got {text!r}") from None


def _faults(text: str) -> FaultSpec:
    try:
        return FaultSpec.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def cmd_carm_sim(args: argparse.Namespace) -> int:
    script = (MotionScript.load(args.script) if args.script is not None
              else MotionScript.from_orbital(args.views, args.hold_s, args.move_s))
    sim = SimulatedCArm(script, args.faults, args.port_link, protocol_version=args.protocol_version)
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with sim:
            link = f" (link {sim.port_link})" if sim.port_link is not None else ""
            print(f"simulated C-arm: protocol v{sim.version} on {sim.pty_name}{link}; open {sim.port} "
                  f"with the encoder link. Stop with Ctrl-C.", flush=True)
            stop.wait(args.duration)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    s = sim.stats
    print(f"simulated C-arm stopped: {s.frames_sent} frames sent ({s.readings_sent} readings), "
          f"{s.requests} requests, {s.overruns} overruns, {s.vanishes} disconnects, {s.stalls} stalls; "
          f"faults: {s.faults.bits_flipped} bits flipped, {s.faults.bytes_dropped} bytes dropped, "
          f"{s.faults.bytes_duplicated} duplicated, {s.faults.noise_bursts} noise bursts", flush=True)
    return 0


def add_carm_sim_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("carm-sim", help="serve the C-arm encoder protocol on a pseudo-terminal",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--port-link", type=Path,
                   help="keep a symlink to the device here (it vanishes and returns with the device)")
    p.add_argument("--faults", type=_faults, default=FaultSpec(), help="fault injection, e.g. "
                   "ber=1e-5,drop=1e-4,dup=1e-4,noise=0.01,stall=300ms/10s,disconnect=0.5/20,garbage,seed=1")
    p.add_argument("--views", type=_angles, default=(0.0, -30.0, 30.0),
                   help="orbital angles of the scripted views, degrees (default 0,-30,30)")
    p.add_argument("--hold-s", type=float, default=3.0, help="seconds at each view")
    p.add_argument("--move-s", type=float, default=2.0, help="seconds to move between views")
    p.add_argument("--script", type=Path, help="a motion script JSON instead of --views")
    p.add_argument("--protocol-version", type=int, default=PROTOCOL_VERSION,
                   help="protocol version the device speaks (to test version errors)")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    p.set_defaults(func=cmd_carm_sim)
