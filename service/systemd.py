"""systemd's notify protocol (``Type=notify``, ``WatchdogSec=``), without a dependency.

A message is one datagram to the unix socket named by ``NOTIFY_SOCKET`` (a leading ``@`` is
the abstract namespace). Outside systemd every call is a no-op. The watchdog interval is
systemd's ``WATCHDOG_USEC``; we ping at half of it, and only while the caller says the
process is healthy, so a dead worker makes systemd kill and restart the service.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable

__all__ = ["notify", "watchdog_interval_s", "Watchdog"]


def notify(message: str) -> bool:
    """Send ``message`` (e.g. ``READY=1``); False outside systemd or if it cannot be sent."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.sendto(message.encode(), address)
    except OSError:
        return False  # systemd gone or the socket unreachable: nothing the service can do
    return True


def watchdog_interval_s() -> float | None:
    """Half of systemd's watchdog timeout for this process, or None if none is set."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        return max(int(usec) / 2e6, 0.05)
    except ValueError:
        return None


class Watchdog:
    """Pings ``WATCHDOG=1`` every ``interval_s`` while ``healthy()`` holds; stops pinging
    (and says why in ``STATUS=``) as soon as it does not."""

    def __init__(self, healthy: Callable[[], bool], interval_s: float):
        self.healthy, self.interval_s = healthy, interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="slamtka-watchdog", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            if not self.healthy():
                notify("STATUS=worker thread not alive: watchdog pings stopped")
                return
            notify("WATCHDOG=1")
