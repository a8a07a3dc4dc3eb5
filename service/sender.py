"""Sending the results: C-STORE to each configured destination through a durable retry queue.

Every (object, destination) pair is a job file in ``queue/pending/`` written crash-safely
before anything is sent, so a restart resumes where it stopped; the job is named after the
pair, so an object queued again (a run repeated after a crash) is still one job. A worker
thread sends the due jobs, one association per destination per round, settling each job as
its answer comes (a crash mid-round re-sends only the object in flight); a failure is retried
with exponential backoff (``retry_initial_s`` doubling up to ``retry_max_s``) and after
``max_attempts`` the job moves to ``queue/failed/``. Every success, failure and abandonment
is in the audit log.

Order: a round sends *every* pending job of a destination, oldest first, once any of them is
due, and while a destination is failing it is probed (TCP, then C-ECHO) every
``retry_initial_s`` (at most 2 s): a
display that comes back gets the queue at once, in order, not after each job's backoff.
A newer run of a case replaces the case's older objects not yet delivered (audited
``send_superseded``): the display should show the latest measurement, not catch up on
stale ones. A refused TCP connection is reported as "connection refused".
"""

from __future__ import annotations

import hashlib
import json
import logging
import socket
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import pydicom
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian
from pynetdicom import AE
from pynetdicom.association import Association

from slamtka.service.atomic_files import remove_partial, write_json_atomic
from slamtka.service.audit import AuditLog
from slamtka.service.config import Destination, SenderConfig, normalise_fingerprint
from slamtka.service.tls import client_ssl_context

__all__ = ["Sender", "SendJob", "OutgoingObject"]

log = logging.getLogger("slamtka.sender")
_MAX_PROBE_S = 2.0  # a failing destination is probed at least this often
_SUCCESS_OR_WARNING = {0x0000, 0x0107, 0x0116, 0xB000, 0xB006, 0xB007}


@dataclass(frozen=True)
class OutgoingObject:
    """One DICOM result object on disk: ``kind`` is ``sr`` or ``sc``."""

    path: Path
    kind: str
    sop_class_uid: str
    sop_instance_uid: str


@dataclass
class SendJob:
    id: str
    destination: str
    path: str
    kind: str
    sop_class_uid: str
    sop_instance_uid: str
    case_id: str
    run_id: str
    created: float
    attempts: int = 0
    next_attempt: float = 0.0
    last_error: str = ""


def _connect_problem(dest: Destination) -> str:
    """Why no association came about, as the network says it (refused, unreachable, ...)."""
    try:
        with socket.create_connection((dest.host, dest.port), timeout=5.0):
            return "association aborted (the port accepts connections)"
    except ConnectionRefusedError:
        return f"connection refused by {dest.host}:{dest.port}"
    except TimeoutError:
        return f"no answer from {dest.host}:{dest.port} (timed out)"
    except OSError as exc:
        return f"cannot connect to {dest.host}:{dest.port} ({exc.strerror or exc})"


class Sender:
    def __init__(self, ae_title: str, destinations: list[Destination], config: SenderConfig,
                 queue_dir: Path, audit: AuditLog):
        self.ae_title, self.config, self.audit = ae_title, config, audit
        self.destinations = {d.name: d for d in destinations}
        self.pending_dir = Path(queue_dir) / "pending"
        self.failed_dir = Path(queue_dir) / "failed"
        self.pending_dir.mkdir(parents=True, exist_ok=True)
        self.failed_dir.mkdir(parents=True, exist_ok=True)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._probed: dict[str, float] = {}  # destination -> when it was last probed
        # Held while a job file is removed by a newer run or rewritten after a failure, so a
        # round still sending a superseded job cannot bring its file back.
        self._jobs_lock = threading.Lock()
        self._probe_s = min(config.retry_initial_s, _MAX_PROBE_S)
        self._thread: threading.Thread | None = None

    # -- queue ------------------------------------------------------------------------------
    def enqueue(self, objects: list[OutgoingObject], case_id: str, run_id: str) -> list[SendJob]:
        jobs = []
        now = time.time()
        self._supersede(case_id, run_id)
        for dest in self.destinations.values():
            for obj in objects:
                if obj.kind not in dest.objects:
                    continue
                pair = f"{dest.name}\0{obj.sop_instance_uid}".encode()
                job = SendJob(hashlib.sha256(pair).hexdigest()[:32], dest.name, str(obj.path),
                              obj.kind, obj.sop_class_uid, obj.sop_instance_uid, case_id, run_id,
                              now)
                write_json_atomic(self.pending_dir / f"{job.id}.json", asdict(job))
                jobs.append(job)
        self._wake.set()
        return jobs

    def _supersede(self, case_id: str, run_id: str) -> None:
        """Drop the case's pending jobs of other (older) runs: a newer result replaces them."""
        for job in self.pending():
            if job.case_id == case_id and job.run_id != run_id:
                with self._jobs_lock:
                    (self.pending_dir / f"{job.id}.json").unlink(missing_ok=True)
                self.audit.record("send_superseded", destination=job.destination,
                                  sop_instance_uid=job.sop_instance_uid, kind=job.kind,
                                  case_id=case_id, run_id=job.run_id, by_run_id=run_id)

    def recover(self) -> int:
        """At start-up: remove what a killed writer left in the queue; how many files."""
        return remove_partial(self.pending_dir) + remove_partial(self.failed_dir)

    def _jobs(self, folder: Path) -> list[SendJob]:
        """The jobs in ``folder``; one settled (removed) while listing is left out, because
        the status board lists the queue while the sender thread works on it."""
        jobs = []
        for path in sorted(folder.glob("*.json")):
            try:
                jobs.append(SendJob(**json.loads(path.read_text())))
            except FileNotFoundError:
                continue
            except (ValueError, TypeError) as exc:  # damaged (a disk error, an edit): named, set aside
                self._set_aside(path, f"unreadable send job: {exc}")
        return sorted(jobs, key=lambda j: (j.created, j.id))

    def _set_aside(self, path: Path, reason: str) -> None:
        """Move a damaged job file to ``queue/damaged/`` (audited), so that one bad file
        neither stops the queue nor the status board that lists it."""
        moved_to = self.pending_dir.parent / "damaged" / f"{path.parent.name}-{path.name}"
        moved_to.parent.mkdir(exist_ok=True)
        try:
            path.replace(moved_to)
        except FileNotFoundError:  # the other lister (sender or status board) was first
            return
        log.error("send queue: %s set aside to %s: %s", path, moved_to, reason)
        self.audit.record("quarantined", file=str(path), reason=reason, moved_to=str(moved_to))

    def pending(self) -> list[SendJob]:
        return self._jobs(self.pending_dir)

    def failed(self) -> list[SendJob]:
        return self._jobs(self.failed_dir)

    # -- sending ----------------------------------------------------------------------------
    def _association(self, dest: Destination, sop_classes: set[str]) -> tuple[Association, str]:
        """The association (maybe not established) and, if TLS failed, why."""
        ae = AE(ae_title=self.ae_title)
        for timeout in ("acse_timeout", "dimse_timeout", "network_timeout", "connection_timeout"):
            setattr(ae, timeout, self.config.timeout_s)
        for sop_class in sorted(sop_classes):
            ae.add_requested_context(sop_class, [ExplicitVRLittleEndian, ImplicitVRLittleEndian])
        if not dest.tls:
            return ae.associate(dest.host, dest.port, ae_title=dest.ae_title), ""
        assert dest.ca_certificates is not None, "the config requires CA certificates with TLS"
        # The certificate must name the host (and be the pinned one, if set).
        ctx = client_ssl_context(dest.ca_certificates, dest.certificate, dest.private_key,
                                 f"destination {dest.name}",
                                 pin_sha256=normalise_fingerprint(dest.certificate_sha256))
        assoc = ae.associate(dest.host, dest.port, ae_title=dest.ae_title,
                             tls_args=(ctx, dest.server_name or dest.host))
        return assoc, ctx.handshake_error

    def _send_to(self, dest: Destination, jobs: list[SendJob], now: float) -> int:
        """Send ``jobs`` over one association to ``dest``; how many were sent. Each job is
        settled as soon as its answer comes, so a crash mid-round re-sends one object, not
        the whole round."""
        try:
            assoc, tls_error = self._association(dest, {j.sop_class_uid for j in jobs})
        except Exception as exc:  # socket/TLS setup errors of every kind end up here
            return sum(self._settle(j, f"cannot connect: {exc}", now) for j in jobs)
        if not assoc.is_established:
            if assoc.is_rejected:
                why = "association rejected"
            elif tls_error:
                why = f"association aborted (TLS: {tls_error})"
            else:
                why = _connect_problem(dest)
            return sum(self._settle(j, why, now) for j in jobs)
        sent, done = 0, 0
        try:
            for job in jobs:
                if not (self.pending_dir / f"{job.id}.json").is_file():
                    done += 1  # superseded by a newer run of its case meanwhile: not sent
                    continue
                try:
                    ds = pydicom.dcmread(job.path)
                except (OSError, pydicom.errors.InvalidDicomError) as exc:
                    error = f"cannot read {job.path}: {exc}"
                else:
                    code = getattr(assoc.send_c_store(ds), "Status", None)
                    error = "" if code in _SUCCESS_OR_WARNING else (
                        "no response" if code is None else f"status 0x{code:04X}")
                sent += self._settle(job, error, now)
                done += 1
        finally:
            if assoc.is_established:
                assoc.release()
            sent += sum(self._settle(j, "not attempted", now) for j in jobs[done:])
        return sent

    def run_once(self, now: float | None = None) -> int:
        """Send, oldest first, every pending job of each destination that has a due job or
        answers a probe again; returns how many were sent."""
        now = time.time() if now is None else now
        pending = self.pending()
        sent = 0
        for name in sorted({j.destination for j in pending}):
            jobs = [j for j in pending if j.destination == name]
            if all(j.next_attempt > now for j in jobs) and not self._back(name, now):
                continue
            dest = self.destinations.get(name)
            if dest is None:
                sent += sum(self._settle(j, f"destination {name!r} is no longer configured", now)
                            for j in jobs)
            else:
                sent += self._send_to(dest, jobs, now)
        return sent

    def _settle(self, job: SendJob, error: str, now: float) -> int:
        path = self.pending_dir / f"{job.id}.json"
        fields = {"destination": job.destination, "sop_instance_uid": job.sop_instance_uid,
                  "kind": job.kind, "case_id": job.case_id, "run_id": job.run_id}
        if not error:
            self.audit.record("sent", attempts=job.attempts + 1, **fields)
            path.unlink(missing_ok=True)
            return 1
        job.attempts += 1
        job.last_error = error
        with self._jobs_lock:
            if not path.is_file():  # superseded by a newer run while it was being sent
                return 0
            return self._retry_or_abandon(job, path, error, fields, now)

    def _retry_or_abandon(self, job: SendJob, path: Path, error: str, fields: dict,
                          now: float) -> int:
        if job.attempts >= self.config.max_attempts:
            write_json_atomic(self.failed_dir / f"{job.id}.json", asdict(job))
            path.unlink(missing_ok=True)
            self.audit.record("send_abandoned", attempts=job.attempts, error=error, **fields)
            log.error("giving up sending %s to %s: %s", job.kind, job.destination, error)
            return 0
        delay = min(self.config.retry_initial_s * 2 ** (job.attempts - 1), self.config.retry_max_s)
        job.next_attempt = now + delay
        write_json_atomic(path, asdict(job))
        self.audit.record("send_failed", attempts=job.attempts, error=error,
                          retry_in_s=round(delay, 3), **fields)
        log.warning("sending %s to %s failed (%s); retry in %.1f s", job.kind, job.destination,
                    error, delay)
        return 0

    def _back(self, name: str, now: float) -> bool:
        """Whether a failing destination answers again (a C-ECHO association, at most every
        ``retry_initial_s``): its queue is then sent at once."""
        dest = self.destinations.get(name)
        if dest is None or now < self._probed.get(name, 0.0) + self._probe_s:
            return False
        self._probed[name] = now
        try:  # the port first: no association attempt (and its error log) while it is closed
            socket.create_connection((dest.host, dest.port), timeout=2.0).close()
            assoc, _ = self._association(dest, {"1.2.840.10008.1.1"})
        except Exception:
            return False
        if not assoc.is_established:
            return False
        assoc.release()
        return True

    # -- worker thread ----------------------------------------------------------------------
    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()
            try:
                self.run_once()
            except Exception:  # keep the worker alive; the job files stay for the next round
                log.exception("sender round failed")
            pending = self.pending()
            upcoming = [j.next_attempt for j in pending]
            probe = [self._probe_s] if pending else []
            wait = min([max(t - time.time(), 0.0) for t in upcoming] + probe + [5.0])
            self._wake.wait(max(wait, 0.01))

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="slamtka-sender", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=self.config.timeout_s + 5)
