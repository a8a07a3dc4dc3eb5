"""Health and metrics: the status snapshot the service keeps, ``slamtka status``, C-ECHO.

The running service rewrites ``status.json`` in its data folder (atomically) on every event
and every few seconds: spool, cases, the last result, the encoder link, the send queue and
counters. ``slamtka status --config FILE`` prints it (``--json`` as is, ``--metrics`` in
the Prometheus text format), and ``--echo`` checks the DICOM side end to end with a C-ECHO
under the health-check AE title (allowed to associate, never to store). Whether the service
is up is judged by :func:`slamtka.service.health.judge` (fresh, running, worker alive); exit
status 0 when it is up (and, with ``--echo``, answered the echo too), 1 otherwise. Counters
carry over a restart: the service starts from the last snapshot's.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import threading
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path

from slamtka.service.atomic_files import write_json_atomic
from slamtka.service.config import ServiceConfig, load_config
from slamtka.service.health import STALE_INTERVALS, judge, prometheus_text
from slamtka.service.tls import client_ssl_context
from slamtka.solver.jsonfile import read_json_object

log = logging.getLogger("slamtka.status")

__all__ = ["Metrics", "StatusBoard", "echo", "read_status", "add_status_parser"]
_COUNTED = {"received": "instances_received", "rejected": "instances_rejected",
            "duplicate": "instances_duplicate", "view_unusable": "views_unusable",
            "association_rejected": "associations_rejected",
            "connection_refused": "connections_refused", "association_aborted": "associations_aborted",
            "context_rejected": "contexts_rejected",
            "case_triggered": "runs_started", "failed": "runs_failed", "sent": "objects_sent",
            "send_failed": "send_failures", "send_abandoned": "sends_abandoned"}


def _as_dict(value: object) -> dict:
    """A carried section, or nothing if a damaged snapshot holds something else there."""
    return value if isinstance(value, dict) else {}


class Metrics:
    """Counters fed by the audit log (one source of truth) and pipeline timings."""

    def __init__(self, carried: dict | None = None) -> None:
        """``carried``: the counters of the previous run's last snapshot, continued from."""
        self.counters: Counter[str] = Counter({name: 0 for name in _COUNTED.values()})
        self.counters.update({"runs_measured": 0, "runs_not_measured": 0})
        for name, value in (carried or {}).items():
            if name in self.counters and isinstance(value, int) and value >= 0:
                self.counters[name] = value
        # refused runs by refusal code (the result's ``refusal.code``), for the metrics
        self.refusals: Counter[str] = Counter(
            {code: n for code, n in _as_dict((carried or {}).get("refusals")).items()
             if isinstance(n, int) and n >= 0})
        self.run_seconds: list[float] = []
        self._lock = threading.Lock()

    def observe(self, entry: dict) -> None:
        """Audit-log listener."""
        with self._lock:
            name = _COUNTED.get(entry["event"])
            if name:
                self.counters[name] += 1
            if entry["event"] == "processed":
                self.counters["runs_measured" if entry.get("status") == "measured"
                              else "runs_not_measured"] += 1
                self.run_seconds.append(float(entry.get("seconds", 0.0)))
                if entry.get("refusal_code"):
                    self.refusals[entry["refusal_code"]] += 1

    def snapshot(self) -> dict:
        with self._lock:
            recent = sorted(self.run_seconds[-100:])
            return {**self.counters, "refusals": dict(sorted(self.refusals.items())),
                    "run_seconds_median": recent[len(recent) // 2] if recent else None,
                    "run_seconds_last": self.run_seconds[-1] if self.run_seconds else None}


class StatusBoard:
    """Builds and writes the status snapshot; ``sources`` are callables returning sections."""

    def __init__(self, path: Path, sources: dict, interval_s: float = 2.0):
        self.path, self.sources, self.interval_s = Path(path), sources, interval_s
        self.last: dict | None = None  # the snapshot last written (the HTTP endpoint reads it)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def refresh(self) -> None:
        """:meth:`write` for the loops: a failure is logged, it never stops the caller (the
        worker or the board's thread), which would leave the service up but idle."""
        try:
            self.write()
        except Exception:
            log.exception("cannot write the status snapshot %s", self.path)

    def write(self) -> dict:
        with self._lock:
            doc = {"updated": datetime.now(UTC).isoformat(timespec="milliseconds"),
                   "stale_after_s": STALE_INTERVALS * self.interval_s, "pid": os.getpid(),
                   **{name: source() for name, source in self.sources.items()}}
            write_json_atomic(self.path, doc)
            self.last = doc
            return doc

    def start(self) -> None:
        def loop() -> None:
            while not self._stop.wait(self.interval_s):
                self.refresh()

        self.write()
        self._thread = threading.Thread(target=loop, name="slamtka-status", daemon=True)
        self._thread.start()

    def stop(self, final: dict | None = None) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.interval_s + 1)
        if final is not None:
            with self._lock:
                write_json_atomic(self.path, final)
                self.last = final


def echo(config: ServiceConfig, host: str | None = None, timeout_s: float = 10.0) -> tuple[bool, str]:
    """C-ECHO to the service under the health-check AE title: (answered, message)."""
    from pynetdicom import AE  # the DICOM stack only when an echo is asked for (start-up time)
    from pynetdicom.sop_class import Verification  # type: ignore[attr-defined]  # made at import

    ae = AE(ae_title=config.dicom.health_ae_title)
    ae.add_requested_context(Verification)
    for name in ("acse_timeout", "dimse_timeout", "network_timeout", "connection_timeout"):
        setattr(ae, name, timeout_s)
    tls = None
    if config.dicom.tls.enabled:
        t = config.dicom.tls
        assert t.ca_certificates is not None, "the config requires CA certificates with TLS"
        # Our own port, dialled by address: the chain is checked, the name cannot be (no
        # server name: ssl takes None, which pynetdicom's hint of tls_args leaves out).
        tls = (client_ssl_context(t.ca_certificates, t.certificate, t.private_key, "dicom.tls",
                                  check_hostname=False), None)
    address = host or ("127.0.0.1" if config.dicom.bind_address in ("0.0.0.0", "::")
                       else config.dicom.bind_address)
    try:
        assoc = ae.associate(address, config.dicom.port, ae_title=config.dicom.ae_title,
                             tls_args=tls)  # type: ignore[arg-type]
    except Exception as exc:  # connection and TLS errors of every kind
        return False, f"cannot connect to {address}:{config.dicom.port}: {exc}"
    if not assoc.is_established:
        return False, f"association with {config.dicom.ae_title}@{address}:{config.dicom.port} refused"
    try:
        status = assoc.send_c_echo()
    finally:
        assoc.release()
    if getattr(status, "Status", None) != 0x0000:
        return False, "C-ECHO failed"
    return True, f"C-ECHO {config.dicom.ae_title}@{address}:{config.dicom.port}: success"


def _describe(status: dict) -> str:
    health = judge(status)
    state = "running" if health.up else f"DOWN: {health.reason}"
    d = status.get("dicom", {})
    lines = [f"slamtka service: {state} (pid {status.get('pid')}, since {status.get('started')})",
             f"  DICOM: {d.get('ae_title')} on {d.get('address')}:{d.get('port')}"
             f"{' with TLS' if d.get('tls') else ''}"]
    spool, queue = status.get("spool", {}), status.get("queue", {})
    lines.append(f"  spool: {spool.get('instances')} instance(s), "
                 f"{(spool.get('bytes') or 0) / 1e6:.1f} MB; send queue: {queue.get('pending')} "
                 f"pending, {queue.get('failed')} failed")
    link = status.get("link") or {}
    lines.append(f"  encoder link: {link.get('status', 'not configured')}"
                 + (f" ({link.get('reason')})" if link.get("reason") else ""))
    cases = status.get("cases") or []
    lines.append(f"  cases: {len(cases)}")
    for c in cases[-5:]:
        lines.append(f"    {c['case_id']}  patient {c['patient_id']}  {c['laterality'] or '-'}  "
                     f"{c['usable_views']}/{c['views']} usable view(s)")
    last = status.get("last_result")
    if last:
        angles = (f"CTR {last['ctr_deg']:+.2f}, STR {last['str_deg']:+.2f} deg, {last['verdict']}"
                  if last.get("ctr_deg") is not None else f"not measured: {last.get('reason')}")
        lines.append(f"  last result: {last['case_id']} at {last['time']}: {angles}")
        lines.append(f"    {last['folder']}")
    m = status.get("metrics") or {}
    lines.append(f"  counters: {m.get('instances_received', 0)} received, "
                 f"{m.get('instances_rejected', 0)} rejected, {m.get('runs_measured', 0)} measured, "
                 f"{m.get('runs_not_measured', 0)} not measured, {m.get('runs_failed', 0)} failed, "
                 f"{m.get('objects_sent', 0)} sent")
    return "\n".join(lines)


def read_status(path: Path) -> dict | None:
    """The status snapshot, None when there is none; a damaged one (e.g. the disk filled
    mid-write) raises naming the file."""
    return read_json_object(path) if path.is_file() else None


def cmd_status(args: argparse.Namespace) -> int:
    # The C-arm's link and kinematics are the service's to check at its start: a health
    # check run every few seconds reads paths and the DICOM section only.
    config = load_config(args.config, drivers=False)
    status = read_status(config.status_file)
    ok = judge(status).up
    if args.metrics:
        print(prometheus_text(status), end="")
    elif status is None:
        print(f"no status at {config.status_file}: the service has not run with this configuration")
    elif args.json:
        print(json.dumps(status, indent=2))
    else:
        print(_describe(status))
    if args.echo:  # both must hold: a port that answers does not make a stale service healthy
        answered, message = echo(config)
        print(message)
        ok = ok and answered
    return 0 if ok else 1


def add_status_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="service health: spool, cases, last result, link, metrics")
    p.add_argument("--config", type=Path, required=True)
    form = p.add_mutually_exclusive_group()
    form.add_argument("--json", action="store_true", help="the raw status snapshot")
    form.add_argument("--metrics", action="store_true", help="Prometheus text format")
    p.add_argument("--echo", action="store_true",
                   help="also C-ECHO the service (exit 1 if it does not answer)")
    p.set_defaults(func=cmd_status)
