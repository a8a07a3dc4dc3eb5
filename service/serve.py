"""``slamtka serve --config FILE``: the long-running service.

Threads: pynetdicom's association threads receive, validate (decode), spool and queue
instances (:mod:`service.scp`; the decoded frame is handed over in memory,
:mod:`service.decoded`); one worker assembles cases and runs the pipeline (so the network side
never waits for the solver); the sender delivers results (:mod:`service.sender`); the
encoder link reads the C-arm (``drivers``); the status board keeps ``status.json`` fresh.

Start-up first takes the data folder's lock (``serve.lock``): a second instance on the same
folder exits at once, touching nothing. It checks everything before the DICOM port opens:
the configuration, the calibration (checksum), the plans folder, the link configuration.
Temporary files a killed predecessor left in the spool and the send queue are removed. Then
the spool is replayed into cases, so a restart loses nothing acknowledged (a damaged spool
file is quarantined and audited, never a reason not to start), and a case whose current
views were not yet measured is measured now.

The worker survives any exception of one item (an audit line that cannot be written
included); should the thread end anyway, ``serve`` exits non-zero so that systemd restarts
it, and the watchdog (``WatchdogSec=``) is pinged only while the worker lives. Under systemd
(``Type=notify``) readiness is signalled once the port is open. SIGTERM/SIGINT stop it
cleanly: the port closes first, the running case finishes, the queues stay on disk.
"""

from __future__ import annotations

import argparse
import fcntl
import logging
import os
import queue
import signal
import sys
import threading
import time
import warnings
from datetime import UTC, datetime
from pathlib import Path

from slamtka.drivers.encoder_link import EncoderLink, LinkConfig
from slamtka.drivers.kinematics import CArmKinematics
from slamtka.service.atomic_files import remove_partial
from slamtka.service.audit import AuditLog, file_digests, last_event
from slamtka.service.cases import Case, CaseAssembler
from slamtka.service.config import ServiceConfig, load_config
from slamtka.service.health import HealthServer, WorkerHeartbeat
from slamtka.service.plans import PlanStore
from slamtka.service.poses import ViewGeometry
from slamtka.service.retention import Retention, pending_case_ids
from slamtka.service.scp import DicomReceiver
from slamtka.service.sender import Sender
from slamtka.service.spool import Spool, SpoolEntry
from slamtka.service.status import Metrics, StatusBoard, read_status
from slamtka.service.story import LinkWatch, tell
from slamtka.service.systemd import Watchdog, notify, watchdog_interval_s
from slamtka.service.workflow import Workflow

__all__ = ["Service", "DataFolderBusy", "lock_data_folder", "supervise", "add_serve_parser"]

log = logging.getLogger("slamtka.serve")
_REQUEST_POLL_S = 0.5  # how soon an idle worker sees an operator's request
EXIT_WORKER_DIED = 70  # EX_SOFTWARE: systemd's Restart=on-failure starts us again
EXIT_DATA_FOLDER_BUSY = 75  # EX_TEMPFAIL: another instance serves this data folder
LOCK_FILE = "serve.lock"


class DataFolderBusy(RuntimeError):
    """Another ``slamtka serve`` holds the data folder."""


def lock_data_folder(data_dir: Path) -> int:
    """Hold ``serve.lock`` in ``data_dir`` (released by the kernel when the process ends);
    the descriptor, or :class:`DataFolderBusy` naming the holder's process id."""
    path = Path(data_dir) / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
        os.close(fd)
        raise DataFolderBusy(f"{data_dir} is in use by another slamtka serve (pid {holder}); "
                             "not starting a second instance on the same data folder") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


class Service:
    def __init__(self, config: ServiceConfig):
        self.config = config
        for folder in (config.data_dir, config.output, config.plans):
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:  # e.g. the path is a file: say which, not a traceback
                raise RuntimeError(f"{folder}: cannot create the service folder "
                                   f"({exc.strerror or exc})") from None
        # Before anything in the folder is opened, repaired or removed.
        self._lock_fd: int | None = lock_data_folder(config.data_dir)
        self.metrics = Metrics(_carried_counters(config.status_file))
        self.audit = AuditLog(config.audit_log, listeners=[self.metrics.observe, tell])
        self.spool = Spool(config.spool_dir)
        # Imported here, not at the top: `slamtka status` (the container's health check) and the
        # other commands then start without loading rerun, highdicom and the imaging chain.
        from slamtka.service.calibrations import CalibrationSet
        from slamtka.service.pipeline import Pipeline

        self.calibrations = CalibrationSet.load(config.data_dir / "calibrations", config.carm.calibration,
                                                config.carm.calibration_match,
                                                on_change=lambda event, fields: self.audit.record(event, **fields))
        kinematics = CArmKinematics.from_config(config.carm.kinematics)
        self.link = None
        self.link_watch = None
        if config.carm.encoder_port:
            self.link_watch = LinkWatch(str(config.carm.encoder_port))
            self.link = EncoderLink(config.carm.encoder_port, LinkConfig.from_config(config.carm.link),
                                    on_state=self.link_watch.on_state)
        geometry = ViewGeometry(kinematics, config.carm.setup, self.link,
                                config.carm.max_reading_age_s, config.carm.angle_check_deg,
                                config.carm.max_clock_offset_s)
        self.plans = PlanStore(config.plans)
        self.pipeline = Pipeline(self.spool, self.plans, self.calibrations, geometry, config.output,
                                 manual_contours_dir=config.pipeline.manual_contours_dir,
                                 institution=config.institution)
        self.assembler = CaseAssembler(self.spool, geometry, config.pipeline.min_view_separation_deg,
                                       config.pipeline.max_views)
        self.sender = Sender(config.dicom.ae_title, config.destinations, config.sender,
                             config.queue_dir, self.audit)
        self.workflow = Workflow(self.pipeline, self.sender, self.audit, config.data_dir,
                                 min_separation_deg=config.pipeline.min_view_separation_deg,
                                 max_views=config.pipeline.max_views,
                                 new_set_on_new_series=config.pipeline.new_set_on_new_series,
                                 institution=config.institution)
        self._incoming: queue.Queue[SpoolEntry | None] = queue.Queue()
        self.retention = Retention(config.retention, config.data_dir, config.output, self.audit.record)
        self._next_retention = 0.0  # at the first turn of the worker, after recovery
        # Cases whose last run was refused for something an operator can add without new
        # views (a plan, a calibration: the refusal's may_restart), by case id, with the code;
        # they run again when the plans or the calibrations change.
        self._waiting: dict[str, str] = {}
        self._inputs_seen = self._inputs_state()
        self.receiver = DicomReceiver(config.dicom, self.spool, self.audit, self._incoming.put,
                                      self.retention.space_problem)
        self._worker: threading.Thread | None = None
        self.heartbeat = WorkerHeartbeat()
        self._watchdog: Watchdog | None = None
        self._state = "starting"
        self._started = datetime.now(UTC).isoformat(timespec="seconds")
        self._last_result = last_event(config.audit_log, "processed")
        self.status = StatusBoard(config.status_file, {
            "state": lambda: self._state, "started": lambda: self._started,
            "dicom": self._dicom_status, "spool": lambda: {"instances": self.spool.count(),
                                                           "bytes": self.spool.bytes_used()},
            "cases": lambda: [c.describe() for c in list(self.assembler.cases.values())],
            "last_result": lambda: self._last_result, "link": self._link_status,
            "queue": lambda: {"pending": len(self.sender.pending()),
                              "failed": len(self.sender.failed())},
            "metrics": self.metrics.snapshot, "calibration": self.calibrations.describe,
            "worker": self._worker_status}, interval_s=config.health.snapshot_interval_s)
        self.health_server = self._health_server(config)

    # -- status sections ------------------------------------------------------------------
    def _dicom_status(self) -> dict:
        d = self.config.dicom
        return {"ae_title": d.ae_title, "address": d.bind_address, "port": self.receiver.port,
                "tls": d.tls.enabled}

    def _health_server(self, config: ServiceConfig) -> HealthServer | None:
        """The HTTP health endpoint; a port already taken costs the endpoint, not the service
        (status.json and `slamtka status` still tell the health)."""
        if not config.health.http_enabled:
            return None
        try:
            return HealthServer(config.health, lambda: self.status.last)
        except OSError as exc:
            log.error("no health endpoint: cannot listen on %s:%d (%s)", config.health.http_bind_address,
                      config.health.http_port, exc.strerror or exc)
            return None

    def _worker_status(self) -> dict:
        return self.heartbeat.describe(self.worker_alive(), self.config.health.max_run_s)

    def _link_status(self) -> dict | None:
        if self.link is None:
            return None
        state = self.link.state
        return {"status": state.status, "reason": state.reason,
                "since": state.since_utc.isoformat(timespec="seconds"),
                "port": self.config.carm.encoder_port}

    def worker_alive(self) -> bool:
        """Whether the worker thread runs (for the watchdog and the health check)."""
        return self._worker is not None and self._worker.is_alive()

    # -- life cycle -----------------------------------------------------------------------
    def start(self) -> None:
        if self.link is not None:
            self.link.start()
        self.pipeline.warm_up()
        partial = remove_partial(self.spool.instances) + self.sender.recover()
        due, quarantined = self._recover()
        self.sender.start()
        try:
            self.receiver.start()
        except OSError as exc:  # address in use or not on this host: stop what started, say so
            self.sender.stop()
            if self.link is not None:
                self.link.stop()
            self._release_lock()
            raise RuntimeError(f"cannot listen for DICOM on {self.config.dicom.bind_address}:"
                               f"{self.config.dicom.port} ({exc.strerror or exc})") from None
        self._worker = threading.Thread(target=self._work, args=(due,), name="slamtka-worker",
                                        daemon=True)
        self._worker.start()
        self._state = "running"
        self.status.start()
        if self.health_server is not None:
            self.health_server.start()
        self.audit.record("service_started", ae_title=self.config.dicom.ae_title,
                          port=self.receiver.port, recovered_instances=self.spool.count(),
                          partial_files_removed=partial, quarantined=quarantined,
                          config=str(self.config.source))
        notify("READY=1")
        interval = watchdog_interval_s()
        if interval is not None:
            self._watchdog = Watchdog(self.worker_alive, interval)
            self._watchdog.start()

    def stop(self) -> None:
        notify("STOPPING=1")
        self._state = "stopping"
        if self._watchdog is not None:
            self._watchdog.stop()
        self.receiver.stop()
        self._incoming.put(None)
        if self._worker is not None:
            self._worker.join()
        self.sender.stop()
        if self.link is not None:
            self.link.stop()
        self._state = "stopped"
        if self.health_server is not None:
            self.health_server.stop()
        if self.link_watch is not None:
            self.link_watch.close()
        self.audit.record("service_stopped")
        self.status.stop(final=self.status.write())
        self.audit.close()
        self._release_lock()

    def _release_lock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def _recover(self) -> tuple[list[Case], int]:
        """Rebuild cases from the spool: (the cases whose current views were not measured,
        how many damaged files were quarantined, each audited with its name and reason)."""
        entries, moved = self.spool.recover()
        for entry in entries:
            try:
                self.spool.read_sidecar(entry)
            except (ValueError, OSError) as exc:  # empty or corrupt: paired again from scratch
                moved.append(self.spool.quarantine(entry.sidecar, f"sidecar unreadable: {exc}"))
            try:
                self.assembler.add(entry)
            except Exception as exc:  # not the size received, an unusable frame: moved aside
                moved.append(self.spool.quarantine(entry.path, f"{type(exc).__name__}: {exc}"))
        for item in moved:
            log.error("quarantined spool file %s: %s", item["file"], item["reason"])
            self.audit.record("quarantined", **item)
        for case in self.assembler.cases.values():
            self.workflow.restore(case)
        due = [c for c in self.assembler.cases.values()
               if self.workflow.is_due(c)
               and not self.pipeline.already_done(c, self.workflow.selection(c))]
        return due, len(moved)

    def _retain(self) -> None:
        """Archive the idle, delivered cases out of the live spool; prune the old ones."""
        pending = pending_case_ids(self.config.queue_dir)
        live = {case_id: [view.entry.path for view in case.views.values()]
                for case_id, case in self.assembler.cases.items()}
        for case_id in self.retention.idle_cases(live, pending):
            self.retention.archive(case_id, live[case_id])
            del self.assembler.cases[case_id]
        self.retention.prune(pending, active=set(self.assembler.cases))

    # -- the worker -----------------------------------------------------------------------
    def _survive(self, what: str, step, *args) -> None:
        """Run one step of the worker; an exception is logged and audited if the log can
        take it (an ENOSPC on the audit log itself must not end the worker)."""
        try:
            step(*args)
        except Exception as exc:
            log.exception("worker: %s failed", what)
            try:
                self.audit.record("failed", step=what, error=f"{type(exc).__name__}: {exc}")
            except Exception:
                log.exception("worker: cannot audit the failure of %s", what)

    def _work(self, due: list[Case]) -> None:
        pending = {c.case_id: c for c in due}  # cases to run, oldest first
        reruns: set[str] = set()  # of those, the ones an operator asked to run again
        while True:
            self.heartbeat.beat()
            batch = []
            if not pending:
                try:  # a timeout, to take the operators' requests (`slamtka case`) when idle
                    batch.append(self._incoming.get(timeout=_REQUEST_POLL_S))
                except queue.Empty:
                    pass
            # Take everything already waiting, so views that arrive together run once.
            while True:
                try:
                    batch.append(self._incoming.get_nowait())
                except queue.Empty:
                    break
            if None in batch:  # stopping; what was spooled is recovered at the next start
                return
            for entry in filter(None, batch):  # (no None left: checked above)
                self._survive(f"assembling {entry.id}", self._assemble, entry, pending)
            self._survive("taking operator requests", self._take_requests, pending, reruns)
            self._survive("re-running cases that waited", self._retry_waiting, pending, reruns)
            if pending:
                case = pending.pop(next(iter(pending)))
                with self.heartbeat.busy(f"case {case.case_id}"):
                    self._survive(f"case {case.case_id}", self._process, case,
                                  case.case_id in reruns)
                reruns.discard(case.case_id)
            if not pending and time.monotonic() >= self._next_retention:
                self._next_retention = time.monotonic() + self.config.retention.interval_s
                self._survive("archiving and pruning", self._retain)
            self._survive("refreshing the status", self.status.refresh)

    def _take_requests(self, pending: dict[str, Case], reruns: set[str]) -> None:
        for case, _ in self.workflow.take_requests(self.assembler.cases):
            pending[case.case_id] = case
            reruns.add(case.case_id)

    def _inputs_state(self) -> tuple[int, ...]:
        """When the plans and the calibrations last changed: their folders' change times (a
        plan or a calibration is added, replaced or removed by a rename into its folder)."""
        stamps = []
        for folder in (self.config.plans, self.config.data_dir / "calibrations"):
            try:
                stamps.append(folder.stat().st_mtime_ns)
            except FileNotFoundError:
                stamps.append(0)
        return tuple(stamps)

    def _retry_waiting(self, pending: dict[str, Case], reruns: set[str]) -> None:
        """Run again, once, the cases refused for a missing plan or calibration when the plans
        or the calibrations changed (``slamtka plan add``, ``slamtka calibration install``)."""
        state = self._inputs_state()
        if state == self._inputs_seen:
            return
        self._inputs_seen = state
        for case_id, code in list(self._waiting.items()):
            del self._waiting[case_id]  # its new run says again whether it still waits
            case = self.assembler.cases.get(case_id)
            if case is not None:
                self.audit.record("rerun_after_change", case_id=case_id, refusal_code=code)
                pending[case_id] = case
                reruns.add(case_id)

    def _assemble(self, entry: SpoolEntry, pending: dict[str, Case]) -> None:
        """Put a received instance into its case and extract its contours ahead of the run."""
        try:
            case, _ = self.assembler.add(entry)
        except Exception as exc:  # one bad instance must not stop the worker; it is audited
            log.exception("cannot assemble instance %s", entry.id)
            self.audit.record("failed", sop_instance_uid=entry.sop_instance_uid,
                              error=f"{type(exc).__name__}: {exc}")
            return
        if case is None:
            return
        view = case.views[entry.sop_instance_uid]
        if view.pairing.clock is not None:
            self.audit.record("clock_mismatch", case_id=case.case_id,
                              sop_instance_uid=entry.sop_instance_uid, **view.pairing.clock)
        if not view.usable:
            # Kept in its case (a later reading or configuration may not help, but nothing
            # received is dropped); said at once, since no run will report it.
            self.audit.record("view_unusable", case_id=case.case_id,
                              sop_instance_uid=entry.sop_instance_uid, reason=view.pairing.problem)
        try:  # extracted now, so that a run triggered later only waits for its last view's
            due = self.workflow.place(case, view)
        except Exception as exc:  # the view stays in its case; the failure is audited
            log.exception("placing instance %s in a pin set failed", entry.id)
            self.audit.record("failed", case_id=case.case_id,
                              sop_instance_uid=entry.sop_instance_uid,
                              error=f"{type(exc).__name__}: {exc}")
            return
        if due:
            pending[case.case_id] = case

    def _process(self, case: Case, rerun: bool = False) -> None:
        views = self.workflow.selection(case)
        if len(views) < 2 or (not rerun and self.pipeline.already_done(case, views)):
            return
        run_id, measurement, triggered = self.workflow.begin_run(case, views, rerun)
        self.audit.record("case_triggered", case_id=case.case_id, run_id=run_id,
                          sop_instance_uids=[v.sop_instance_uid for v in views],
                          separation_deg=round(case.separation_deg(views), 2),
                          pin_set=measurement["pin_set"], number=measurement["number"],
                          rerun=rerun)
        try:
            outcome = self.pipeline.run(
                case, views, on_output=lambda obj: self.sender.enqueue([obj], case.case_id, run_id),
                run_id=run_id, measurement=measurement, triggered=triggered,
                min_separation_deg=self.config.pipeline.min_view_separation_deg)
        except Exception as exc:  # one bad case must not stop the service; it is audited
            log.exception("case %s run %s failed", case.case_id, run_id)
            self.audit.record("failed", case_id=case.case_id, run_id=run_id,
                              error=f"{type(exc).__name__}: {exc}")
            return
        result, angles, refusal = outcome.result, outcome.result.angles, outcome.result.refusal
        self.workflow.finish_run(case, run_id, result)
        if refusal is not None and refusal.may_restart:
            self._waiting[case.case_id] = refusal.code.value
        else:
            self._waiting.pop(case.case_id, None)
        self._last_result = self.audit.record(
            "processed", case_id=case.case_id, run_id=run_id, pin_set=measurement["pin_set"],
            number=measurement["number"], status=result.status,
            verdict=result.verdict, reason=result.reason,
            refusal_code=None if refusal is None else refusal.code.value,
            ctr_deg=None if angles is None else angles.ctr_deg,
            str_deg=None if angles is None else angles.str_deg,
            seconds=result.timings["total_s"],
            folder=str(outcome.folder), outputs_sha256=file_digests(outcome.folder))


def _carried_counters(status_file: Path) -> dict:
    """The counters of the previous run's last snapshot (none if it is absent or damaged)."""
    try:
        previous = read_status(status_file)
    except (OSError, ValueError) as exc:
        log.warning("counters start at 0: %s", exc)
        return {}
    metrics = (previous or {}).get("metrics")
    return metrics if isinstance(metrics, dict) else {}


def _service_logging(verbose: bool) -> None:
    """INFO for the service's own story (DEBUG with --verbose); the DICOM libraries only when
    something needs attention: not a line per association or per built object."""
    logging.getLogger().setLevel(logging.DEBUG if verbose else logging.INFO)
    for chatty in ("pynetdicom", "highdicom"):
        logging.getLogger(chatty).setLevel(logging.WARNING)
    # highdicom warns of legal but unusual values it is given (names of one component): not
    # the operator's business, and the values are kept as received.
    warnings.filterwarnings("ignore", category=UserWarning, module="highdicom")


def cmd_serve(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    _service_logging(args.verbose)
    try:
        service = Service(config)
    except DataFolderBusy as exc:
        print(f"slamtka serve: {exc}", file=sys.stderr, flush=True)
        return EXIT_DATA_FOLDER_BUSY
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    service.start()
    print(f"slamtka serving DICOM as {config.dicom.ae_title} on {config.dicom.bind_address}:"
          f"{service.receiver.port}; data in {config.data_dir}"
          + (f"; health on http://{config.health.http_bind_address}:{service.health_server.port}"
             if service.health_server is not None else ""), flush=True)
    return supervise(service, stop)


def supervise(service: Service, stop: threading.Event, poll_s: float = 1.0) -> int:
    """Run until ``stop`` is set or the worker thread ends (then the process must go, so
    that systemd starts it afresh); stop the service; the exit status."""
    while not stop.wait(poll_s):
        if not service.worker_alive():
            log.critical("the worker thread ended; exiting (status %d) to be restarted",
                         EXIT_WORKER_DIED)
            service.stop()
            return EXIT_WORKER_DIED
    service.stop()
    return 0


def add_serve_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the service (DICOM SCP, pipeline, results)")
    p.add_argument("--config", type=Path, required=True, help="service configuration (TOML)")
    p.set_defaults(func=cmd_serve)
