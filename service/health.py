"""The service's health, judged one way for every reader.

``slamtka status`` (and the container's health check), its ``--metrics`` text, and the
service's own HTTP endpoint (``/healthz``, Prometheus ``/metrics``) all ask :func:`judge`
about a status snapshot. Up means: the service says it is running, its snapshot is fresh
(the board rewrites it every ``snapshot_interval_s``; three missed writes and it is stale,
so a killed service is seen as down within seconds), and the worker thread is alive and not
stuck in one run longer than any run may take.
"""

from __future__ import annotations

import contextlib
import http.server
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime

from slamtka.service.config import HealthConfig

log = logging.getLogger("slamtka.health")

__all__ = ["Health", "WorkerHeartbeat", "judge", "prometheus_text", "HealthServer", "STALE_INTERVALS"]

STALE_INTERVALS = 3  # a snapshot missed this many times over is stale


def _utc(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, UTC).isoformat(timespec="milliseconds")


class WorkerHeartbeat:
    """The worker's pulse: a beat per loop, and what it is busy with while a run lasts."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last_beat = time.time()
        self._busy: tuple[str, float] | None = None

    def beat(self) -> None:
        with self._lock:
            self._last_beat = time.time()

    @contextlib.contextmanager
    def busy(self, what: str) -> Iterator[None]:
        with self._lock:
            self._busy = (what, time.time())
        try:
            yield
        finally:
            with self._lock:
                self._busy = None
                self._last_beat = time.time()

    def describe(self, alive: bool, max_run_s: float) -> dict:
        with self._lock:
            busy = self._busy
            return {"alive": alive, "last_beat": _utc(self._last_beat), "max_run_s": max_run_s,
                    "busy_with": busy[0] if busy else None,
                    "busy_since": _utc(busy[1]) if busy else None}


@dataclass(frozen=True)
class Health:
    up: bool
    reason: str  # "running", or why the service is not


def _age_s(stamp: str, now: datetime) -> float:
    return (now - datetime.fromisoformat(stamp)).total_seconds()


def judge(status: dict | None, now: datetime | None = None) -> Health:
    """Whether the service that wrote ``status`` is up, and if not, why."""
    if status is None:
        return Health(False, "no status snapshot: the service has not run with this configuration")
    now = now or datetime.now(UTC)
    state = status.get("state", "unknown")
    if state != "running":
        return Health(False, f"the service is {state}")
    try:
        age = _age_s(status["updated"], now)
    except (KeyError, TypeError, ValueError):
        return Health(False, "the status snapshot has no valid update time")
    stale_after = float(status.get("stale_after_s", 30.0))
    if age > stale_after:
        return Health(False, f"not responding: last update {age:.0f} s ago "
                             f"(stale after {stale_after:.0f} s; killed or hung?)")
    worker = status.get("worker")
    if not isinstance(worker, dict) or not worker.get("alive"):
        return Health(False, "the worker thread is not running: received frames are not measured")
    if worker.get("busy_since"):
        busy_s = _age_s(worker["busy_since"], now)
        if busy_s > float(worker.get("max_run_s", 120.0)):
            return Health(False, f"the worker is stuck: busy with {worker.get('busy_with')} for "
                                 f"{busy_s:.0f} s")
    return Health(True, "running")


def _families(status: dict | None) -> Iterator:
    """The snapshot as Prometheus metric families (prometheus_client's own types)."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    health = judge(status)
    yield GaugeMetricFamily("slamtka_up", "1 when the service is running, fresh and its worker "
                            "alive", value=int(health.up))
    status = status or {}
    metrics = dict(status.get("metrics") or {})
    refusals = CounterMetricFamily("slamtka_refusals", "refused runs by refusal code",
                                   labels=["code"])
    for code, count in sorted((metrics.pop("refusals", None) or {}).items()):
        refusals.add_metric([code], count)
    yield refusals
    for name, value in sorted(metrics.items()):
        if value is None:
            continue
        if not name.startswith("run_seconds"):  # the run times are gauges, the rest counts
            yield CounterMetricFamily(f"slamtka_{name}", name.replace("_", " "), value=value)
        else:
            yield GaugeMetricFamily(f"slamtka_{name}", name.replace("_", " "), value=value)
    gauges = {"spool_instances": (status.get("spool") or {}).get("instances"),
              "send_queue_pending": (status.get("queue") or {}).get("pending"),
              "send_queue_failed": (status.get("queue") or {}).get("failed"),
              "cases": len(status.get("cases") or [])}
    for name, value in gauges.items():
        if value is not None:
            yield GaugeMetricFamily(f"slamtka_{name}", name.replace("_", " "), value=value)
    link = (status.get("link") or {}).get("status")
    if link:
        yield GaugeMetricFamily("slamtka_encoder_link_connected", "1 when the encoder link is up",
                                value=int(link == "connected"))


class _SnapshotCollector:
    def __init__(self, snapshot: Callable[[], dict | None]) -> None:
        self._snapshot = snapshot

    def collect(self) -> Iterator:
        yield from _families(self._snapshot())


def _exposition(snapshot: Callable[[], dict | None]) -> bytes:
    from prometheus_client import CollectorRegistry, generate_latest

    registry = CollectorRegistry(auto_describe=False)
    registry.register(_SnapshotCollector(snapshot))
    return generate_latest(registry)


def prometheus_text(status: dict | None) -> str:
    """The snapshot in the Prometheus text exposition format (``slamtka status --metrics``)."""
    return _exposition(lambda: status).decode()


class HealthServer:
    """``GET /healthz`` (200 ok / 503 with the reason) and ``GET /metrics`` over HTTP."""

    def __init__(self, config: HealthConfig, snapshot: Callable[[], dict | None]) -> None:
        from prometheus_client import CONTENT_TYPE_LATEST

        def respond(handler: http.server.BaseHTTPRequestHandler) -> None:
            if handler.path == "/healthz":
                health = judge(snapshot())
                code, body, kind = (200 if health.up else 503), (health.reason + "\n").encode(), \
                    "text/plain; charset=utf-8"
            elif handler.path == "/metrics":
                code, body, kind = 200, _exposition(snapshot), CONTENT_TYPE_LATEST
            else:
                code, body, kind = 404, b"not found: /healthz or /metrics\n", "text/plain"
            handler.send_response(code)
            handler.send_header("Content-Type", kind)
            handler.send_header("Content-Length", str(len(body)))
            handler.end_headers()
            handler.wfile.write(body)

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (the standard library's name)
                respond(self)

            def log_message(self, format: str, *args: object) -> None:  # scrapes are not news
                log.debug("health endpoint: " + format, *args)

        self._server = http.server.ThreadingHTTPServer(
            (config.http_bind_address, config.http_port), Handler)
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, name="slamtka-health",
                                        daemon=True)

    @property
    def port(self) -> int:
        return self._server.server_address[1]

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()
