"""The device's end of a simulated serial cable: a pty pair behind a stable symlink.

A twin owns the master side and publishes the slave through a symlink (as udev's
``/dev/serial/by-id/...`` does for a USB-serial adapter), so the client opens a real tty
with pyserial, and an unplug is a real one: the master is closed and the link removed, the
client's reads hit EOF and its writes EIO, reopening fails with ENOENT until ``plug`` makes
a new pty and points the link at it. The actuator boards and the simulated USB-CAN adapter
of the PC104 link both stand on it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import tty

# How a vehicle file names a simulated board's port (``sim://steering``) until the twin's
# pty stands behind it; a client is only ever given the resolved tty path.
SIM_PORT_PREFIX = "sim://"


class PtyLink:
    """The device's end of a simulated serial cable."""

    def __init__(self, link_path: str) -> None:
        self.link_path = link_path
        self.slave_path: str | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self.tx_bytes = 0
        self.tx_dropped_bytes = 0  # nobody reading (UART with no listener): bytes are lost
        self.plug()

    @property
    def master_fd(self) -> int | None:
        """The twin's end (for an event loop's ``add_reader``); None while unplugged."""
        return self._master

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def plug(self) -> None:
        if self._master is not None:
            return
        master, slave = os.openpty()
        # Raw before anyone opens it: a cooked tty would echo our telemetry back to us.
        tty.setraw(slave)
        flags = fcntl.fcntl(master, fcntl.F_GETFL)
        fcntl.fcntl(master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self._master, self._slave = master, slave
        self.slave_path = os.ttyname(slave)
        # We keep the slave open too: otherwise the master reads EIO whenever the client
        # closes, and the twin would see a client reconnect as its own unplug.
        temporary = f"{self.link_path}.new"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        os.symlink(self.slave_path, temporary)
        os.replace(temporary, self.link_path)

    def unplug(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.link_path)
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None
        self.slave_path = None

    def read(self) -> bytes:
        """Everything the client sent since the last call (empty when unplugged)."""
        if self._master is None:
            return b""
        chunks: list[bytes] = []
        while True:
            try:
                chunk = os.read(self._master, 4096)
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno == errno.EIO:
                    break
                raise
            if not chunk:
                break
            chunks.append(chunk)
        return b"".join(chunks)

    def write(self, data: bytes) -> int:
        """Send what fits; the rest is lost, as on a UART whose receiver is not reading."""
        if self._master is None:
            self.tx_dropped_bytes += len(data)
            return 0
        try:
            written = os.write(self._master, data)
        except BlockingIOError:
            written = 0
        except OSError as exc:
            if exc.errno != errno.EIO:
                raise
            written = 0
        self.tx_bytes += written
        self.tx_dropped_bytes += len(data) - written
        return written
