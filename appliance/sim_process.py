"""The built-in simulated vehicle in a process of its own, started and stopped by the daemon.

Why: the world, two LMS111 twins (ray casting and telegram encoding at 50 Hz each), the
PC104 twin and four boards are a vehicle's worth of work. Sharing the daemon's event
loop, they made the control loop miss cycles and its inputs go stale on an idle 2-core
machine: the daemon was measured under a load no vehicle puts on it. In a child process
the simulation has a CPU of its own and the daemon reaches it exactly as it reaches
hardware: the scanners over TCP, the boards on ptys, the PC104 through a (simulated)
SLCAN USB-CAN adapter on a pty, because python-can's ``virtual`` bus does not cross
processes and these machines have no kernel CAN.

The child is ``dbw sim`` itself, so what the daemon runs is what a developer can run by
hand. It is one supervised service: if it dies, its inputs go stale, the safety layer
holds the vehicle safe, and the supervisor starts a new one with backoff. It exits when
the daemon does, however the daemon ends: its stdin is a pipe from the daemon, and
end-of-file on it (the daemon gone, even by SIGKILL) stops it.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import signal
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from appliance.config import VehicleConfig
from appliance.config.loader import to_toml
from appliance.config.models import CanEndpoint
from appliance.logs import current_log_settings, get_logger
from drivers.pc104.endpoint import CanInterface
from drivers.ptylink import SIM_PORT_PREFIX

log = get_logger("sim_process")

READY_TIMEOUT_S = 30.0  # imports and site set-up; a cold machine takes a few seconds
# The daemon's own shutdown is bounded (safety.shutdown_grace_s, 0.6 s by default) and a
# simulation has nothing to save: SIGTERM, and SIGKILL if it is not gone by then.
STOP_GRACE_S = 0.3
CAN_ADAPTER_NAME = "pc104-can"
BENCH_SOCKET_NAME = "bench.sock"
# The child runs this much nicer than the daemon: on a machine with fewer free cores than
# runnable processes the scheduler hands a core to the control loop's wake-up first, as
# it would to the daemon on the vehicle, where the simulated world does not exist.
SIM_NICE_INCREMENT = 5
BOARD_NAMES = ("steering", "throttle", "brake", "panel")
# The child's twins behind ``sim://NAME`` ports, each a tty symlink in its directory (the
# GNSS/INS receiver's only when the config's devices.gnss.port asks for it).
SIM_PORT_NAMES = (*BOARD_NAMES, "gnss")


def lower_priority(pid: int, increment: int) -> int | None:
    """Make ``pid`` ``increment`` nicer than this process; its niceness, or None if the
    system refused (the child then competes as an equal, which is only slower)."""
    try:
        nice = min(os.getpriority(os.PRIO_PROCESS, 0) + increment, 19)
        os.setpriority(os.PRIO_PROCESS, pid, nice)
    except OSError as exc:
        log.warning("sim_process_priority_unchanged", pid=pid, error=str(exc))
        return None
    return nice


class SimProcessError(RuntimeError):
    """The simulated vehicle's process did not come up, or ended."""


class SimProcess:
    """One child process running the world and every twin of ``config``.

    The paths are fixed before the child exists, so the daemon's clients are built
    against them at once and simply reconnect until the child has made them.
    """

    def __init__(
        self,
        config: VehicleConfig,
        directory: str | None = None,
        *,
        python: str = sys.executable,
        ready_timeout_s: float = READY_TIMEOUT_S,
    ) -> None:
        self.config = config
        self._own_directory = directory is None
        self.directory = directory or tempfile.mkdtemp(prefix="dbw-sim-")
        self.python = python
        self.ready_timeout_s = ready_timeout_s
        self.pid: int | None = None
        self.starts = 0

    def port_path(self, port: str) -> str:
        """``sim://NAME`` -> the tty symlink the child's twin publishes (a board, or gnss)."""
        name = port.removeprefix(SIM_PORT_PREFIX)
        if not port.startswith(SIM_PORT_PREFIX) or name not in SIM_PORT_NAMES:
            raise ValueError(f"no simulated device for port {port!r}; known: {SIM_PORT_NAMES}")
        return os.path.join(self.directory, name)

    @property
    def can_endpoint(self) -> CanEndpoint | None:
        """Where the daemon's PC104 client finds the child's simulated USB-CAN adapter;
        None for a vehicle without a PC104 (speed by pedals), whose child runs no PC104 twin."""
        if self.config.speed_path != "pc104":
            return None
        return CanEndpoint(
            interface=CanInterface.SLCAN,
            channel=os.path.join(self.directory, CAN_ADAPTER_NAME),
            bitrate_bps=500_000,
        )

    @property
    def bench_path(self) -> str:
        """The child's bench socket (:mod:`appliance.sim.bench`): tests and benchmarks act
        as the operator and flip the twins' fault switches through it."""
        return os.path.join(self.directory, BENCH_SOCKET_NAME)

    def command(self, config_file: str, ready_fd: int) -> list[str]:
        level, as_json = current_log_settings()
        can = self.can_endpoint
        can_args = [] if can is None else ["--can-slcan", can.channel]
        return [
            self.python,
            "-m",
            "appliance",
            "--log-level",
            level,
            "--log-format",
            "json" if as_json else "console",
            "sim",
            "--config",
            config_file,
            "--pty-dir",
            self.directory,
            *can_args,
            "--ready-fd",
            str(ready_fd),
            "--exit-on-stdin-eof",
            "--bench-socket",
            self.bench_path,
        ]

    async def run(self, beat: Callable[[], None]) -> None:
        """Start the child, beat while it lives; raise when it ends (the supervisor restarts)."""
        config_file = os.path.join(self.directory, "vehicle.toml")
        text = to_toml(self.config.model_dump(mode="json")) + "\n"
        await asyncio.to_thread(Path(config_file).write_text, text, encoding="utf-8")
        ready_r, ready_w = os.pipe()
        try:
            proc = await asyncio.create_subprocess_exec(
                *self.command(config_file, ready_w),
                stdin=asyncio.subprocess.PIPE,
                pass_fds=(ready_w,),
                start_new_session=True,  # a Ctrl-C at the terminal is the daemon's to handle
            )
        finally:
            os.close(ready_w)
        self.pid = proc.pid
        lower_priority(proc.pid, SIM_NICE_INCREMENT)
        self.starts += 1
        exited: asyncio.Future[int] = asyncio.ensure_future(proc.wait())
        try:
            await self._await_ready(proc, exited, ready_r, beat)
            log.info("sim_process_ready", pid=proc.pid, directory=self.directory)
            while not exited.done():
                beat()
                await asyncio.wait({exited}, timeout=0.1)
            raise SimProcessError(
                f"simulated vehicle process {proc.pid} exited ({proc.returncode})"
            )
        finally:
            os.close(ready_r)
            await self._stop(proc, exited)

    async def _await_ready(
        self,
        proc: asyncio.subprocess.Process,
        exited: asyncio.Future[int],
        ready_r: int,
        beat: Callable[[], None],
    ) -> None:
        loop = asyncio.get_running_loop()
        ready: asyncio.Future[bytes] = loop.create_future()

        def on_readable() -> None:
            if not ready.done():
                ready.set_result(os.read(ready_r, 64))

        loop.add_reader(ready_r, on_readable)
        deadline_s = loop.time() + self.ready_timeout_s
        try:
            while not ready.done():
                if exited.done() and not ready.done():
                    raise SimProcessError(
                        f"simulated vehicle process exited ({proc.returncode}) before it was ready"
                    )
                if loop.time() > deadline_s:
                    raise SimProcessError(
                        f"simulated vehicle process not ready within {self.ready_timeout_s:.0f} s"
                    )
                beat()
                either: set[asyncio.Future[Any]] = {ready, exited}
                await asyncio.wait(either, timeout=0.1)
        finally:
            loop.remove_reader(ready_r)
        if not ready.result().startswith(b"ready"):
            raise SimProcessError(
                f"simulated vehicle process failed to start (exit {await exited})"
            )

    async def _stop(self, proc: asyncio.subprocess.Process, exited: asyncio.Future[int]) -> None:
        """SIGTERM, then SIGKILL after a grace period; never leaves a child behind."""
        if proc.stdin is not None:
            proc.stdin.close()
        killed = False
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            await asyncio.wait({exited}, timeout=STOP_GRACE_S)
            if not exited.done():
                killed = True
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await exited
        log.info("sim_process_stopped", pid=proc.pid, exit_code=proc.returncode, killed=killed)
        self.pid = None

    def close(self) -> None:
        """Remove the directory of ptys and the child's config (after the service ended)."""
        if self._own_directory:
            shutil.rmtree(self.directory, ignore_errors=True)
