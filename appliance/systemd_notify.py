"""systemd's notify protocol (READY, WATCHDOG, STATUS, STOPPING) through libsystemd.

cysystemd wraps libsystemd's own ``sd_notify``, so abstract sockets and the protocol's
details are systemd's, not ours. Outside systemd (no ``NOTIFY_SOCKET``) every call is a
cheap no-op, so the daemon runs the same from a terminal.
"""

from __future__ import annotations

import os

from appliance.logs import get_logger

log = get_logger("systemd")


class SystemdNotifier:
    def __init__(self) -> None:
        self.enabled = bool(os.environ.get("NOTIFY_SOCKET"))
        self.watchdog_interval_s = self._watchdog_interval_s()
        self._last_status = ""

    @staticmethod
    def _watchdog_interval_s() -> float | None:
        """WatchdogSec= as systemd passes it, if it is meant for this process."""
        usec = os.environ.get("WATCHDOG_USEC")
        pid = os.environ.get("WATCHDOG_PID")
        if not usec:
            return None
        if pid and pid != str(os.getpid()):
            return None
        try:
            value = int(usec)
        except ValueError:
            log.warning("bad_watchdog_usec", value=usec)
            return None
        return value / 1e6 if value > 0 else None

    def _send(self, line: str) -> None:
        if not self.enabled:
            return
        from cysystemd.daemon import Notification, notify

        name, _, value = line.partition("=")
        notification = Notification[name]
        if notification.value.constant is not None:
            result = notify(notification)
        else:
            result = notify(notification, value)
        if isinstance(result, Exception):
            log.warning("sd_notify_failed", line=line, error=str(result))

    def ready(self) -> None:
        self._send("READY=1")

    def watchdog(self) -> None:
        self._send("WATCHDOG=1")

    def stopping(self) -> None:
        self._send("STOPPING=1")

    def status(self, text: str) -> None:
        """Send STATUS= only when it changed: it is what `systemctl status` shows."""
        if text != self._last_status:
            self._last_status = text
            self._send(f"STATUS={text}")
