"""A stand-in for systemd's notify socket, for tests and benchmarks.

It binds a Unix datagram socket, records every message with the monotonic time it
arrived, and gives the environment a service manager would set (NOTIFY_SOCKET,
WATCHDOG_USEC), so the daemon's real sd_notify path is exercised end to end.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType


@dataclass(frozen=True)
class Notification:
    at_s: float  # time.monotonic() on arrival
    line: str


class FakeNotifySocket:
    def __init__(self, directory: Path) -> None:
        self.path = directory / "notify.sock"
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(self.path))
        self._sock.settimeout(0.05)
        self._lock = threading.Lock()
        self._messages: list[Notification] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._receive, name="fake-notify", daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            now_s = time.monotonic()
            with self._lock:
                for line in data.decode("utf-8", "replace").splitlines():
                    self._messages.append(Notification(now_s, line))

    def environment(
        self, watchdog_s: float | None = None, pid: int | None = None
    ) -> dict[str, str]:
        env = {"NOTIFY_SOCKET": str(self.path)}
        if watchdog_s is not None:
            env["WATCHDOG_USEC"] = str(int(watchdog_s * 1e6))
            if pid is not None:
                env["WATCHDOG_PID"] = str(pid)
        return env

    @property
    def messages(self) -> list[Notification]:
        with self._lock:
            return list(self._messages)

    def lines(self, prefix: str = "") -> list[Notification]:
        return [m for m in self.messages if m.line.startswith(prefix)]

    def wait_for(self, prefix: str, timeout_s: float = 5.0, after_s: float = -1.0) -> Notification:
        deadline_s = time.monotonic() + timeout_s
        while time.monotonic() < deadline_s:
            for message in self.lines(prefix):
                if message.at_s > after_s:
                    return message
            time.sleep(0.005)
        raise TimeoutError(f"no {prefix!r} within {timeout_s} s; got {self.messages}")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self._sock.close()
        if self.path.exists():
            os.unlink(self.path)

    def __enter__(self) -> FakeNotifySocket:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
