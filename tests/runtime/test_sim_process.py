"""The daemon with its simulated vehicle in a child process, as `dbw run --config sim` runs.

The child is reached as hardware (TCP, ptys, an SLCAN adapter on a pty); these tests check
that the daemon comes up on it, engages, goes safe when the child dies, gets a new child
from the supervisor, and never leaves one behind.
"""

from __future__ import annotations

import asyncio
import math
import os
import signal
import socket
import tempfile
from collections.abc import Callable
from pathlib import Path

from appliance.config import VehicleConfig, load_config
from appliance.daemon import Daemon
from appliance.modes import Mode
from appliance.sim_process import SIM_NICE_INCREMENT


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def process_sim_config() -> VehicleConfig:
    """The sim profile as shipped (placement = process), on free scanner ports."""
    config = load_config("sim")
    devices = config.devices.model_copy(
        update={
            "lms111_left": config.devices.lms111_left.model_copy(update={"port": free_port()}),
            "lms111_right": config.devices.lms111_right.model_copy(update={"port": free_port()}),
        }
    )
    return config.model_copy(update={"devices": devices})


async def wait_until(predicate: Callable[[], bool], timeout_s: float) -> None:
    async def poll() -> None:
        while not predicate():
            await asyncio.sleep(0.01)

    await asyncio.wait_for(poll(), timeout_s)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


async def test_daemon_engages_on_the_child_process_and_leaves_no_child_behind() -> None:
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")
    daemon = Daemon(process_sim_config(), control_socket=str(Path(directory) / "control.sock"))
    io = daemon.io
    assert io.simulator is None and io.sim_process is not None
    assert io.pc104 is not None
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        await wait_until(lambda: daemon.core.state.mode is Mode.READY, 30.0)
        pid = io.sim_process.pid
        assert pid is not None and alive(pid)
        # The simulated world yields the CPU to the daemon (see SIM_NICE_INCREMENT).
        assert os.getpriority(os.PRIO_PROCESS, pid) == min(
            os.getpriority(os.PRIO_PROCESS, 0) + SIM_NICE_INCREMENT, 19
        )
        health = io.pc104.health()
        assert health.connected and not health.stale  # the PC104 over SLCAN
        ages = io.topics.ages_s(asyncio.get_running_loop().time())
        for name in ("scan.left", "scan.right", "board.steering", "pc104.status"):
            assert ages[name] < 0.2, (name, ages)
        # dbw status names who held the event loop longest.
        event_loop = daemon.status_document()["event_loop"]
        assert event_loop["callbacks"] > 0 and event_loop["longest_callback_by"]
        assert event_loop["since_start"]["longest_callback_ms"] >= event_loop["longest_callback_ms"]

        # READY can come a few cycles before the PC104 hears our commands (it says so
        # with its command timeout, and engagement is refused meanwhile): press until
        # engagement is accepted, as an operator would.
        def engage() -> bool:
            ok, _ = daemon.core.request("engage", daemon.clock())
            return ok

        await wait_until(engage, 15.0)
        await wait_until(lambda: daemon.core.state.mode is Mode.ENGAGED, 15.0)
    finally:
        daemon.request_stop("test over")
        result = await asyncio.wait_for(run, 10.0)
    assert result.exit_code == 0, result.reason
    assert not alive(pid)
    assert not await asyncio.to_thread(os.path.exists, io.sim_process.directory)


async def test_a_dead_child_holds_the_vehicle_safe_and_the_supervisor_starts_a_new_one() -> None:
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")
    daemon = Daemon(process_sim_config(), control_socket=str(Path(directory) / "control.sock"))
    io = daemon.io
    assert io.sim_process is not None
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        await wait_until(lambda: daemon.core.state.mode is Mode.READY, 30.0)
        first = io.sim_process.pid
        assert first is not None
        os.kill(first, signal.SIGKILL)
        # Its inputs go stale: the core faults and holds safe.
        await wait_until(lambda: daemon.core.state.mode is Mode.ERROR, 15.0)
        output = daemon.core.last_output
        assert output is not None
        assert not output.throttle.enable and output.brake.enable
        assert any(f.reason.startswith("stale:") for f in daemon.core.state.faults)
        # A new child comes up and the inputs are fresh again.
        await wait_until(
            lambda: (
                io.sim_process is not None
                and io.sim_process.pid not in (None, first)
                and io.sim_process.starts >= 2
            ),
            30.0,
        )
        loop = asyncio.get_running_loop()

        def fresh() -> bool:
            ages = io.topics.ages_s(loop.time())
            return all(
                math.isfinite(ages[n]) and ages[n] < 0.2
                for n in ("scan.left", "board.steering", "pc104.status")
            )

        await wait_until(fresh, 30.0)
        assert daemon.supervisor.latched_error is None
        second = io.sim_process.pid
    finally:
        daemon.request_stop("test over")
        result = await asyncio.wait_for(run, 10.0)
    assert result.exit_code == 0, result.reason
    assert second is not None and not alive(second)
