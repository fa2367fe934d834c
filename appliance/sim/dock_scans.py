"""The simulated flat-bed's two scanners for `dbw sim dock`: rendered in order, here or in
a forked worker on the other core.

A scan's beams are rendered from the truth at one instant, which stands for the middle
of the mirror's sweep; a real LMS111 sends the scan when the sweep is over and the
telegram is out, about half a scan period later (the 270° field is 3/4 of the turn, and
the transfer adds a few ms). `run_dock` delivers each scan that much later, stamped
with the instant it was taken, as the daemon receives them. That latency is also what
lets two cores share an approach: nothing the localizer and controller do before a
scan is delivered can move the truth it was rendered from, so the world renders scan k
while the localizer works on scan k−1.

The worker changes when a scan is rendered, never what it is: the requests are served
in order, from the same noise generators and ray caches, so a run with the worker is
the same run as one without it, to the last bit (a test holds them equal).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
import traceback
from collections import deque
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Protocol

import numpy as np

from appliance.perception.types import FloatArray
from appliance.sim.scanner_errors import ScannerErrors
from appliance.sim.scanner_model import RayCache, render_scan
from appliance.sim.site import Site
from drivers.geometry import Pose2D

_STOP = b""  # the request that ends the worker
# The first byte of a reply: ranges follow, or the worker's traceback.
_RANGES, _FAILED = b"R", b"F"


@dataclass
class ScanRenderer:
    """Both scanners' world: the site, and per scanner its configured mount, its drawn
    errors, its noise generator and its ray cache (the state a run's scans depend on)."""

    site: Site
    mounts: dict[str, Pose2D]
    errors: dict[str, ScannerErrors]
    rngs: dict[str, np.random.Generator]
    caches: dict[str, RayCache]
    step_rad: float

    def render(self, name: str, t_s: float, truth: Pose2D) -> FloatArray:
        """The ranges scanner ``name`` measures with the platform at ``truth``."""
        ranges, _ = render_scan(
            self.site, t_s, truth, self.mounts[name], rng=self.rngs[name],
            errors=self.errors[name], step_rad=self.step_rad, cache=self.caches[name],
        )  # fmt: skip
        return ranges


class Scans(Protocol):
    """Scans asked for in order and taken in the same order."""

    def submit(self, name: str, t_s: float, truth: Pose2D) -> None: ...

    def take(self) -> FloatArray: ...

    def close(self) -> None: ...


class InlineScans:
    """Each scan rendered when it is asked for."""

    def __init__(self, renderer: ScanRenderer) -> None:
        self._renderer = renderer
        self._done: deque[FloatArray] = deque()

    def submit(self, name: str, t_s: float, truth: Pose2D) -> None:
        self._done.append(self._renderer.render(name, t_s, truth))

    def take(self) -> FloatArray:
        return self._done.popleft()

    def close(self) -> None:
        self._done.clear()


class WorkerScans:
    """The renderer in a forked process: `submit` returns at once, `take` waits for the
    oldest scan asked for.

    Forked, not spawned: the child starts with the renderer as it stands (no pickling,
    no second import of numpy, which would cost a short run most of its time). A worker
    that fails sends its traceback, and `take` raises it here; one whose parent is gone
    reads the end of the pipe and exits.
    """

    def __init__(self, renderer: ScanRenderer) -> None:
        context = multiprocessing.get_context("fork")
        self._conn, child = context.Pipe()
        self._process = context.Process(
            target=_serve, args=(renderer, child, self._conn), daemon=True, name="dock-scans"
        )
        self._process.start()
        child.close()

    def submit(self, name: str, t_s: float, truth: Pose2D) -> None:
        request = np.array([t_s, truth.x_m, truth.y_m, truth.yaw_rad], dtype=np.float64)
        # A worker that has exited is reported by `take`, in the scans' order.
        with contextlib.suppress(OSError):
            self._conn.send_bytes(name.encode() + b"\n" + request.tobytes())

    def take(self) -> FloatArray:
        try:
            reply = self._conn.recv_bytes()
        except (EOFError, OSError):
            raise RuntimeError("the scan renderer exited without a scan") from None
        if reply[:1] != _RANGES:
            raise RuntimeError("the scan renderer failed:\n" + reply[1:].decode(errors="replace"))
        # A writable copy, as the inline renderer's own array is.
        return np.frombuffer(reply, dtype=np.float64, offset=1).copy()

    def close(self) -> None:
        with contextlib.suppress(OSError):  # a worker already gone
            self._conn.send_bytes(_STOP)
        self._process.join(timeout=5.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._conn.close()


def _serve(renderer: ScanRenderer, conn: Connection, parent_end: Connection) -> None:
    parent_end.close()  # so that the parent's exit is an end of file here
    # Ctrl-C is the parent's to handle: it closes the worker (or its exit is our EOF).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while True:
        try:
            request = conn.recv_bytes()
        except EOFError:
            return
        if request == _STOP:
            return
        try:
            name, _, numbers = request.partition(b"\n")
            t_s, x_m, y_m, yaw_rad = np.frombuffer(numbers, dtype=np.float64).tolist()
            ranges = renderer.render(name.decode(), t_s, Pose2D(x_m, y_m, yaw_rad))
            conn.send_bytes(_RANGES + np.ascontiguousarray(ranges, dtype=np.float64).tobytes())
        except Exception:
            conn.send_bytes(_FAILED + traceback.format_exc().encode())
            return


def open_scans(renderer: ScanRenderer, worker: bool) -> Scans:
    """A worker if asked for and this process may have one (it can fork, and is not a
    daemonic process, which may have no children), else inline."""
    if (
        worker
        and "fork" in multiprocessing.get_all_start_methods()
        and not multiprocessing.current_process().daemon
    ):
        return WorkerScans(renderer)
    return InlineScans(renderer)
