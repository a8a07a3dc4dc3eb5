"""``slamtka bench hardening --out DIR``: hostile input, admission and disk-full, counted.

Each item runs against a real :class:`~service.scp.DicomReceiver` on loopback (fresh data
folder) and counts the inputs tried and the failures: a hostile input that was acknowledged,
a refusal that was not audited, a hang, a server that stopped serving, memory growth of
256 MB or more, or (fuzzing) anything in the spool that does not pass validation again.
The tests run every item with small counts; the command runs the large ones and writes
``hardening.json``. Attackers use other loopback addresses (127.0.0.2 ...) than the C-arm
(127.0.0.1), as other hosts would. The crash, fault and soak items run the whole service
as its own process (:mod:`service.bench_faults`); the TLS-name, AE-squatting, compressed-syntax
and pixel-layout items are in :mod:`service.bench_network`.
"""

from __future__ import annotations

import argparse
import json
import resource
import signal
import ssl
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import psutil
import pydicom
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian

from slamtka.bench.hostile import (
    DEFLATED,
    Dropped,
    RawAssociation,
    deflate_bomb,
    element_length_cases,
    frame_dataset_bytes,
    malformed_pdus,
    mutations,
    nested_sequence,
    pdata,
    pixel_length_cases,
    store_command,
    truncations,
    uid_cases,
    with_uid,
)
from slamtka.bench.pki import client_context, make_pki
from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.config import config_from_dict
from slamtka.service.frames import XA_IMAGE_STORAGE, decode_frame
from slamtka.service.scp import DicomReceiver, check_instance
from slamtka.service.spool import Spool, entry_id

__all__ = ["ServiceUnderTest", "ITEMS", "run_items", "add_hardening_bench_parser"]

MEMORY_LIMIT_MB = 256.0
REFUSALS = ("rejected", "connection_refused", "association_rejected", "association_aborted")


@dataclass
class ServiceUnderTest:
    """A receiver on loopback in its own folder, and what it spooled."""

    root: Path
    dicom: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        table = {"dicom": {"port": 0, "allowed_calling_ae_titles": ["CARM1"],
                           "max_pdu_bytes": 65536, "max_message_bytes": 8 << 20, **self.dicom},
                 "carm": {"calibration": "unused.json"}}
        self.config = config_from_dict(table, environ={})
        self.audit = AuditLog(self.root / "audit.jsonl")
        self.stored: list = []
        self.receiver = DicomReceiver(self.config.dicom, Spool(self.root / "spool"), self.audit,
                                      self.stored.append)
        self.receiver.start()

    @property
    def port(self) -> int:
        return self.receiver.port

    def quiet(self, timeout_s: float = 10.0) -> None:
        """Wait until the server has closed every connection (it frees them asynchronously)."""
        deadline = time.monotonic() + timeout_s
        while self.receiver._server.open_connections and time.monotonic() < deadline:
            time.sleep(0.02)

    def refusals(self) -> int:
        return sum(e["event"] in REFUSALS for e in read_audit(self.audit.path))

    def serving(self) -> bool:
        """The C-arm can still associate and C-ECHO."""
        try:
            assoc = RawAssociation(self.port).associate()
            ok = assoc.echo() == 0
            assoc.release()
            return ok
        except (Dropped, OSError):
            return False

    def stop(self) -> None:
        self.receiver.stop()
        self.audit.close()


@dataclass
class Tally:
    tried: int = 0
    failures: int = 0
    notes: dict = field(default_factory=dict)

    def count(self, failed: bool, why: str = "") -> None:
        self.tried += 1
        if failed:
            self.failures += 1
            self.notes.setdefault("failed", [])
            if len(self.notes["failed"]) < 20:
                self.notes["failed"].append(why)


class PeakRss:
    """Samples this process's resident memory every few milliseconds; the growth in MB."""

    def __enter__(self) -> PeakRss:
        self._proc, self._stop = psutil.Process(), threading.Event()
        self.start = self.peak = self._proc.memory_info().rss
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(0.005):
            self.peak = max(self.peak, self._proc.memory_info().rss)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def growth_mb(self) -> float:
        return (self.peak - self.start) / 1e6


def _refused_store(tally: Tally, target: ServiceUnderTest, dataset: bytes, uid: str, why: str,
                   context_id: int = 1, command_uid: str | None = None) -> None:
    """One store on a fresh association that must get a failure status (or, for a command
    that cannot be decoded, an A-ABORT)."""
    try:
        assoc = RawAssociation(target.port).associate()
        status = assoc.store(dataset, uid, context_id, command_uid=command_uid)
        assoc.release()
        tally.count(status < 0xA000 and status not in (0x0122, 0x0124), f"{why}: 0x{status:04X}")
    except Dropped as exc:
        tally.count(not exc.aborted, f"{why}: dropped ({exc})")


def _with_audit(run: Callable[[Tally, ServiceUnderTest, int], None]):
    """Every refusal must be audited and the server must still serve afterwards."""
    def item(target: ServiceUnderTest, count: int) -> Tally:
        tally, before = Tally(), target.refusals()
        run(tally, target, count)
        audited = target.refusals() - before
        if audited < tally.tried - tally.failures:
            tally.failures += tally.tried - tally.failures - audited
            tally.notes["unaudited"] = tally.tried - audited
        if not target.serving():
            tally.failures += 1
            tally.notes["stopped_serving"] = True
        return tally
    item.__name__ = run.__name__
    return item


# -- hostile and broken DICOM ------------------------------------------------------------

@_with_audit
def uids(tally: Tally, target: ServiceUnderTest, count: int) -> None:
    cases = uid_cases()
    for i in range(count):
        name, command_uid, dataset_uid = cases[i % len(cases)]
        explicit = i % 2 == 0
        data, _ = frame_dataset_bytes(i, 16, explicit)
        data = with_uid(data, dataset_uid, explicit)
        _refused_store(tally, target, data, dataset_uid, name, 1 if explicit else 3, command_uid)
    spool = target.root / "spool" / "instances"
    strays = [p for p in target.root.rglob("*") if p.is_file() and p.parent != spool
              and p.name != "audit.jsonl"]
    escaped = [p for p in (Path("/tmp/slamtka-escape"), Path("/tmp/slamtka-escape.dcm"))
               if p.exists()]
    tally.notes["files_outside_spool"] = len(strays) + len(escaped)
    tally.failures += len(strays) + len(escaped) + len(list(spool.glob("*")))


@_with_audit
def truncation(tally: Tally, target: ServiceUnderTest, count: int) -> None:
    for explicit in (True, False):
        data, uid = frame_dataset_bytes(1, 16, explicit)
        for cut in truncations(data, max(10, count // 2)):
            _refused_store(tally, target, data[:cut], uid, f"cut at {cut}", 1 if explicit else 3)


def _named_cases(make: Callable[[bytes, bool], list[tuple[str, bytes]]], seed: int):
    """An item storing each (name, dataset) case ``make`` builds from a valid frame."""
    def run(tally: Tally, target: ServiceUnderTest, count: int) -> None:
        for explicit in (True, False):
            data, uid = frame_dataset_bytes(seed, 16, explicit)
            for name, mutant in make(data, explicit)[:max(1, count)]:
                _refused_store(tally, target, mutant, uid, name, 1 if explicit else 3)
    return _with_audit(run)


pixel_length = _named_cases(pixel_length_cases, 2)
element_length = _named_cases(element_length_cases, 3)


@_with_audit
def nesting(tally: Tally, target: ServiceUnderTest, count: int) -> None:
    with PeakRss() as rss:
        for depth in (9, 1000, 10000)[:max(1, count)]:
            for explicit in (True, False):
                data, uid = frame_dataset_bytes(4, 16, explicit)
                _refused_store(tally, target, nested_sequence(data, depth, explicit), uid,
                               f"depth {depth}", 1 if explicit else 3)
    tally.notes["memory_growth_mb"] = round(rss.growth_mb, 1)
    tally.failures += rss.growth_mb >= MEMORY_LIMIT_MB


def _dropped_or_refused(assoc: RawAssociation, send: Callable[[], int]) -> tuple[bool, str]:
    """True if the server refused (failure status) or dropped the connection."""
    try:
        status = send()
    except Dropped as exc:
        return True, str(exc)
    finally:
        assoc.close()
    return status >= 0xA000, f"status 0x{status:04X}"


@_with_audit
def deflate(tally: Tally, target: ServiceUnderTest, count: int) -> None:
    """1 MB inflating to 1 GiB, on the (refused) deflated context and on an accepted one."""
    bomb = deflate_bomb()
    _, uid = frame_dataset_bytes(5, 16)
    with PeakRss() as rss:
        for i in range(max(1, count)):
            contexts = [(1, XA_IMAGE_STORAGE, [ExplicitVRLittleEndian]),
                        (7, XA_IMAGE_STORAGE, [DEFLATED]), (5, "1.2.840.10008.1.1",
                                                            [ImplicitVRLittleEndian])]
            assoc = RawAssociation(target.port, contexts=contexts).associate()
            refused_context = 7 not in assoc.accepted
            context = 7 if i % 2 == 0 else 1
            ok, why = _dropped_or_refused(assoc, lambda a=assoc, c=context: a.store(bomb, uid, c))
            tally.count(not (ok and refused_context), why)
    tally.notes["memory_growth_mb"] = round(rss.growth_mb, 1)
    tally.notes["bomb_bytes"] = len(bomb)
    tally.failures += rss.growth_mb >= MEMORY_LIMIT_MB


@_with_audit
def oversize(tally: Tally, target: ServiceUnderTest, count: int) -> None:
    """A PDU declaring 4 GiB; a dataset streamed as legal PDUs to 512 MiB: both dropped early."""
    _, uid = frame_dataset_bytes(6, 16)
    chunk = bytes(60000)
    stream_bytes = 512 << 20
    with PeakRss() as rss:
        for i in range(max(2, count)):
            assoc = RawAssociation(target.port).associate()
            sent = 0

            def push(assoc: RawAssociation = assoc, huge_pdu: bool = i % 2 == 0) -> int:
                nonlocal sent
                assoc.send(pdata(1, store_command(XA_IMAGE_STORAGE, uid), True, True))
                if huge_pdu:
                    assoc.send(b"\x04\x00\xff\xff\xff\xf0")  # a P-DATA-TF of ~4 GiB ...
                    while sent < stream_bytes:  # ... of which we send up to 512 MiB
                        assoc.send(chunk)
                        sent += len(chunk)
                else:
                    frame = pdata(1, chunk, False, False)
                    while sent < stream_bytes:
                        assoc.send(frame)
                        sent += len(chunk)
                return 0x0000
            ok, why = _dropped_or_refused(assoc, push)
            tally.count(not ok or sent >= stream_bytes, why)
            tally.notes.setdefault("bytes_sent_before_drop", []).append(sent)
    tally.notes["memory_growth_mb"] = round(rss.growth_mb, 1)
    tally.failures += rss.growth_mb >= MEMORY_LIMIT_MB


def _consistent(path: Path) -> bool:
    """A spooled file passes validation again and sits under its UID's digest."""
    try:
        ds = pydicom.dcmread(path)
        uid = str(ds.SOPInstanceUID)
        syntax = ds.file_meta.TransferSyntaxUID
        if check_instance(ds, str(ds.SOPClassUID), syntax, uid) is not None:
            return False
        decode_frame(ds)
        return path.stem == entry_id(uid)
    except Exception:
        return False


def fuzz_datasets(target: ServiceUnderTest, count: int) -> Tally:
    """Mutated valid datasets over one association; crashes and inconsistent spool entries."""
    tally = Tally()
    kinds: dict[str, int] = {}
    seeds = [(explicit, *frame_dataset_bytes(7 + explicit, 16, explicit)) for explicit in (True, False)]
    assoc = RawAssociation(target.port).associate()
    accepted = 0
    for i, (explicit, data, uid) in enumerate(seeds):
        share = count // 2 + (count % 2 if i == 0 else 0)
        for kind, mutant in mutations(data, share, seed=i):
            kinds[kind] = kinds.get(kind, 0) + 1
            try:
                status = assoc.store(mutant, uid, 1 if explicit else 3)
                accepted += status == 0
                tally.count(False)
            except Dropped as exc:
                tally.count(True, f"{kind}: dropped ({exc})")
                assoc = RawAssociation(target.port).associate()
    assoc.release()
    spooled = list((target.root / "spool" / "instances").glob("*.dcm"))
    bad = [p.name for p in spooled if not _consistent(p)]
    tally.failures += len(bad)
    tally.failures += not target.serving()
    tally.notes.update(kinds=kinds, acknowledged=accepted, spooled=len(spooled),
                       inconsistent_in_spool=len(bad))
    return tally


def fuzz_protocol(target: ServiceUnderTest, count: int) -> Tally:
    """Malformed PDUs, each on a fresh connection; the server must keep serving."""
    tally = Tally()
    for kind, data, after in malformed_pdus(count, seed=11):
        try:
            assoc = RawAssociation(target.port, source="127.0.0.9", timeout_s=10.0)
            assoc.associate() if after else assoc.connect()
            assoc.send(data)
            try:
                pdu_type, _ = assoc.read_pdu()
                failed = pdu_type == 0x02 and not after  # a mutated request may still be valid
                failed = False if failed else pdu_type == 0x04  # data answered to garbage
            except Dropped:
                failed = False
            assoc.close()
        except Dropped:
            failed = False
        except TimeoutError:
            failed = True
        tally.count(failed, kind)
    tally.failures += not target.serving()
    return tally


# -- who may talk to it ------------------------------------------------------------------

def admission(target: ServiceUnderTest, count: int) -> Tally:
    """Wrong calling/called AE, a source address off the list, per-peer and association caps."""
    tally = Tally()
    for _ in range(max(1, count)):
        target.quiet()
        before = target.refusals()
        for calling, called, source in (("INTRUDER", "SLAMTKA", None), ("CARM1", "OTHER", None),
                                        ("CARM1", "SLAMTKA", "127.0.0.66")):
            try:
                RawAssociation(target.port, calling=calling, called=called, source=source).associate()
                tally.count(True, f"{calling}->{called} from {source} associated")
            except Dropped:
                tally.count(False)
        limits = target.config.dicom
        held = [RawAssociation(target.port, source="127.0.0.3").connect()
                for _ in range(limits.max_connections_per_peer)]
        try:
            extra = RawAssociation(target.port, source="127.0.0.3").associate()
            tally.count(True, "connection beyond the per-peer limit associated")
            extra.close()
        except Dropped:
            tally.count(False)
        for sock in held:
            sock.close()
        carms = [RawAssociation(target.port).associate() for _ in range(limits.max_associations)]
        try:
            RawAssociation(target.port).associate()
            tally.count(True, "association beyond the limit accepted")
        except Dropped:
            tally.count(False)
        for assoc in carms:
            assoc.release()
        audited = target.refusals() - before
        tally.failures += max(0, 5 - audited)
    return tally


def tls_matrix(target: ServiceUnderTest, count: int, pki: dict) -> Tally:
    """No certificate, wrong CA, expired, TLS 1.1, plain TCP: refused and audited."""
    tally = Tally()

    def context(cert: str | None, maximum=None) -> ssl.SSLContext:
        return client_context(pki, cert, maximum)

    cases = [("no client certificate", context(None)), ("wrong CA", context("rogue")),
             ("expired certificate", context("expired")),
             ("TLS 1.1", context("client", ssl.TLSVersion.TLSv1_1)), ("plain TCP", None)]
    for _ in range(max(1, count)):
        before = target.refusals()
        assoc = RawAssociation(target.port, tls=context("client")).associate()
        tally.count(assoc.echo() != 0, "valid client refused")
        assoc.release()
        for name, ctx in cases:
            try:
                raw = RawAssociation(target.port, tls=ctx).associate()
                ok = raw.echo() == 0
                raw.close()
                tally.count(ok, f"{name} associated")
            except (Dropped, OSError):
                tally.count(False)
        time.sleep(0.2)  # the server audits after the client has given up
        tally.failures += max(0, len(cases) - (target.refusals() - before))
    return tally


def idle_flood(target: ServiceUnderTest, count: int, idle: int = 200, busy: int = 50,
               bound_s: float = 2.0) -> Tally:
    """``idle`` silent sockets and ``busy`` hammering clients; the C-arm associates in time."""
    tally, stop = Tally(), threading.Event()
    per_peer = target.config.dicom.max_connections_per_peer
    sockets = [RawAssociation(target.port, source=f"127.0.2.{1 + i // per_peer}").connect()
               for i in range(idle)]

    def hammer(n: int) -> None:
        source = f"127.0.3.{1 + n}"
        while not stop.is_set():
            try:
                assoc = RawAssociation(target.port, source=source, timeout_s=5.0,
                                       calling="INTRUDER" if n % 2 else "SLAMTKA_HEALTH")
                assoc.associate()
                assoc.echo()
                assoc.release()
            except (Dropped, OSError):
                time.sleep(0.01)

    threads = [threading.Thread(target=hammer, args=(n,), daemon=True) for n in range(busy)]
    for t in threads:
        t.start()
    time.sleep(0.5)
    latencies = []
    try:
        for _ in range(max(1, count)):
            start = time.perf_counter()
            try:
                assoc = RawAssociation(target.port, timeout_s=10.0).associate()
                ok = assoc.echo() == 0
                assoc.release()
            except (Dropped, OSError):
                ok = False
            latencies.append(time.perf_counter() - start)
            tally.count(not ok or latencies[-1] > bound_s, f"{latencies[-1]:.2f} s, ok={ok}")
            time.sleep(0.05)
    finally:
        stop.set()
        for t in threads:
            t.join()
        for raw in sockets:
            raw.close()
    tally.notes.update(idle_sockets=idle, busy_clients=busy, bound_s=bound_s,
                       max_latency_s=round(max(latencies), 3),
                       median_latency_s=round(sorted(latencies)[len(latencies) // 2], 3))
    return tally


# -- faults ------------------------------------------------------------------------------

@contextmanager
def file_size_limit(limit: int) -> Iterator[None]:
    """Writes past ``limit`` bytes fail (EFBIG) as on a full disk; main thread only."""
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)


def disk_full(target: ServiceUnderTest, count: int) -> Tally:
    """While writes fail: 0xA700, nothing spooled, no partial file; then the same stores succeed."""
    tally = Tally()
    frames = [frame_dataset_bytes(100 + i, 512) for i in range(max(1, count))]
    spool = target.root / "spool" / "instances"
    assoc = RawAssociation(target.port).associate()
    with file_size_limit(256 * 1024):
        for data, uid in frames:
            status = assoc.store(data, uid)
            tally.count(status != 0xA700, f"status 0x{status:04X} while the disk was full")
    leftovers = len(list(spool.iterdir()))
    for data, uid in frames:
        status = assoc.store(data, uid)
        tally.count(status != 0x0000, f"status 0x{status:04X} after space returned")
    assoc.release()
    tally.failures += leftovers
    tally.failures += len(list(spool.glob("*.dcm"))) != len(frames)
    tally.notes.update(partial_files=leftovers, spooled_after_recovery=len(list(spool.glob("*.dcm"))))
    return tally


ITEMS = ("uids", "truncation", "pixel_length", "element_length", "nesting", "deflate",
         "oversize", "fuzz_datasets", "fuzz_protocol", "admission", "tls", "idle_flood",
         "disk_full")


def _receiver_item(name: str, folder: Path, count: int, bound_s: float) -> Tally:
    """One receiver item against a fresh :class:`ServiceUnderTest` in ``folder``."""
    simple = {"uids": uids, "truncation": truncation, "pixel_length": pixel_length,
              "element_length": element_length, "nesting": nesting, "deflate": deflate,
              "oversize": oversize, "fuzz_datasets": fuzz_datasets, "fuzz_protocol": fuzz_protocol,
              "disk_full": disk_full}
    dicom: dict = {}
    if name == "admission":
        dicom = {"allowed_source_addresses": ["127.0.0.1", "127.0.0.3"],
                 "max_connections_per_peer": 4, "max_associations": 2}
    if name == "tls":
        pki = make_pki(folder / "pki")
        dicom = {"tls": {"enabled": True, "certificate": str(pki["server_cert"]),
                         "private_key": str(pki["server_key"]), "ca_certificates": str(pki["ca"])}}
    target = ServiceUnderTest(folder, dicom)
    try:
        if name == "tls":
            return tls_matrix(target, count, pki)
        if name == "admission":
            return admission(target, count)
        if name == "idle_flood":
            return idle_flood(target, count, bound_s=bound_s)
        return simple[name](target, count)
    finally:
        target.stop()


def run_items(root: Path, counts: dict[str, float], bound_s: float = 2.0,
              log: Callable[[str], None] = lambda _: None) -> dict[str, dict]:
    """Run each item in ``counts`` in its own folder under ``root``: the receiver items
    against a fresh receiver, the fault items (:mod:`service.bench_faults`) against the
    whole service."""
    from slamtka.bench.faults import FAULT_ITEMS, run_fault_item  # they build on this module
    from slamtka.bench.network import NETWORK_ITEMS, run_network_item
    from slamtka.bench.storage import STORAGE_ITEMS, run_storage_item

    results = {}
    for name, count in counts.items():
        folder = root / name
        folder.mkdir(parents=True, exist_ok=True)
        started = time.perf_counter()
        if name in FAULT_ITEMS or name == "soak":
            tally = run_fault_item(name, folder, count)
        elif name in NETWORK_ITEMS:
            tally = run_network_item(name, folder, int(count))
        elif name in STORAGE_ITEMS:
            tally = run_storage_item(name, folder, int(count))
        else:
            tally = _receiver_item(name, folder, int(count), bound_s)
        results[name] = {"tried": tally.tried, "failures": tally.failures, **tally.notes,
                         "seconds": round(time.perf_counter() - started, 1)}
        log(f"{name:15s} tried {tally.tried:7d}  failures {tally.failures}")
    return results


_LARGE = {"uids": 200, "truncation": 400, "pixel_length": 20, "element_length": 20,
          "nesting": 3, "deflate": 4, "oversize": 4, "fuzz_datasets": 100000,
          "fuzz_protocol": 10000, "admission": 5, "tls": 5, "idle_flood": 40, "disk_full": 5,
          "crash": 1000, "destination_down": 20, "serial_faults": 6,
          "tls_names": 5, "ae_squatting": 20, "compressed": 20, "pixel_layouts": 20,
          "enospc": 3, "damaged_spool": 8, "uid_conflict": 50, "second_instance": 3,
          "burst_memory": 24, "retention": 1000}


def run_hardening_bench(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    everything = not args.only and args.soak is None
    counts: dict[str, float] = {k: v for k, v in _LARGE.items()
                                if everything or k in (args.only or ())}
    if args.soak is not None:
        counts["soak"] = args.soak
    if args.fuzz is not None:
        counts.update({k: args.fuzz for k in ("fuzz_datasets",) if k in counts})
    # tmpfs if there is one: the audit log fsyncs every refusal, 100,000 times
    shm = "/dev/shm" if Path("/dev/shm").is_dir() else None
    with tempfile.TemporaryDirectory(prefix="slamtka-hardening-", dir=shm) as tmp:
        results = run_items(Path(tmp), counts, log=lambda line: print(line, flush=True))
    (out / "hardening.json").write_text(json.dumps({"items": results}, indent=2))
    total = sum(r["failures"] for r in results.values())
    print(f"{sum(r['tried'] for r in results.values())} inputs, {total} failures; "
          f"wrote {out / 'hardening.json'}")
    return 0 if total == 0 else 1


def add_hardening_bench_parser(kinds: argparse._SubParsersAction) -> None:
    from slamtka.bench.faults import FAULT_ITEMS
    from slamtka.bench.network import NETWORK_ITEMS
    from slamtka.bench.storage import STORAGE_ITEMS

    p = kinds.add_parser("hardening", help="hostile DICOM, admission, TLS, floods, disk full, "
                                                "crashes, faults, soak, TLS names, AE "
                                                "squatting, compressed syntaxes, pixel layouts")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--only", type=lambda s: s.split(","),
                   help=f"items (of {', '.join(ITEMS + FAULT_ITEMS + NETWORK_ITEMS + STORAGE_ITEMS)})")
    p.add_argument("--fuzz", type=int, help="mutation-fuzzed datasets (default 100000)")
    p.add_argument("--soak", type=float, metavar="MINUTES",
                   help="soak the service: a frame a second, a malformed input a minute (only "
                        "this, and the --only items)")
    p.set_defaults(func=run_hardening_bench)
