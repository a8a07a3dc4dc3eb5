"""The service log tells each case's story, one line per step.

An operator reading ``journalctl -u slamtka`` sees, for every case, the frames received, the
run triggered, its result or refusal with the reason, and each object sent — told from the
audit events (the one record of what happened), so the log and the audit trail never
disagree. Everything else of the service logs at DEBUG unless it needs someone's attention.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from slamtka.drivers.encoder_link import LinkState

log = logging.getLogger("slamtka.case")

__all__ = ["tell", "LinkWatch"]


def _who(e: dict) -> str:
    return f"case {e.get('case_id', '?')}" + (f" run {e['run_id']}" if e.get("run_id") else "")


def _processed(e: dict) -> str:
    if e.get("ctr_deg") is None:
        return f"{_who(e)}: not measured: {e.get('reason')}"
    return (f"{_who(e)}: measured CTR {e['ctr_deg']:+.2f}, STR {e['str_deg']:+.2f} deg, "
            f"{e.get('verdict')} ({e.get('seconds', 0.0):.2f} s)")


_STEPS: dict[str, tuple[int, Callable[[dict], str]]] = {
    "received": (logging.INFO, lambda e: f"received {e['sop_instance_uid']} from "
                                         f"{e.get('calling_ae')} at {e.get('peer')}"),
    "rejected": (logging.WARNING, lambda e: f"refused {e.get('sop_instance_uid')} from "
                                            f"{e.get('calling_ae')}: {e.get('reason')}"),
    "view_unusable": (logging.WARNING, lambda e: f"{_who(e)}: view {e['sop_instance_uid']} "
                                                 f"cannot be used: {e.get('reason')}"),
    "pin_set_started": (logging.INFO, lambda e: f"{_who(e)}: new pin set {e.get('pin_set')} "
                                                f"({e.get('reason')})"),
    "case_triggered": (logging.INFO, lambda e: f"{_who(e)}: triggered with "
                                               f"{len(e.get('sop_instance_uids', []))} views "
                                               f"{e.get('separation_deg')} deg apart"),
    "processed": (logging.INFO, _processed),
    "failed": (logging.ERROR, lambda e: f"{_who(e)}: failed: {e.get('error')}"),
    "status_sent": (logging.INFO, lambda e: f"{_who(e)}: display told: {e.get('message')}"),
    "sent": (logging.INFO, lambda e: f"{_who(e)}: {e.get('kind')} sent to {e.get('destination')}"),
    "rerun_after_change": (logging.INFO, lambda e: f"{_who(e)}: run again now that the plans or "
                                                   f"calibrations changed (it was refused: "
                                                   f"{e.get('refusal_code')})"),
    "calibrations_reloaded": (logging.INFO, lambda e: f"calibrations changed: added {e.get('added')}, "
                                                      f"replaced {e.get('replaced')}, removed {e.get('removed')}"),
    "calibrations_unreadable": (logging.ERROR, lambda e: f"calibrations folder unreadable, still using "
                                                         f"{e.get('kept')}: {e.get('error')}"),
}


def tell(entry: dict) -> None:
    """Audit-log listener: the line of this step of a case's story, if it is one."""
    step = _STEPS.get(entry["event"])
    if step is not None:
        level, line = step
        log.log(level, line(entry))


class LinkWatch:
    """The encoder link's state, logged only when it matters: a drop that lasts longer than
    ``patience_s`` is a WARNING (and its recovery INFO); brief flaps stay at DEBUG."""

    def __init__(self, port: str, patience_s: float = 10.0) -> None:
        self.port, self.patience_s = port, patience_s
        self._timer: threading.Timer | None = None
        self._warned = False
        self._lock = threading.Lock()

    def on_state(self, state: LinkState) -> None:
        """The link's callback (from its reader thread; the link itself logs every change at
        DEBUG)."""
        with self._lock:
            if state.status in ("connected", "stopped"):
                if self._timer is not None:
                    self._timer.cancel()
                    self._timer = None
                if self._warned:
                    log.info("encoder link %s: connected again", self.port)
                    self._warned = False
            elif self._timer is None and not self._warned:
                since = time.monotonic()
                self._timer = threading.Timer(self.patience_s, self._warn, (state.reason, since))
                self._timer.daemon = True
                self._timer.start()

    def _warn(self, reason: str, since: float) -> None:
        with self._lock:
            self._timer, self._warned = None, True
        log.warning("encoder link %s: down for %.0f s (%s): views taken now have no encoder "
                    "reading", self.port, time.monotonic() - since, reason)

    def close(self) -> None:
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
