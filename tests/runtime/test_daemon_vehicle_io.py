"""The daemon on the built-in simulated vehicle: its drivers talk to the twins for real."""

from __future__ import annotations

import asyncio

from appliance.config import load_config
from appliance.config.models import ColaDialect
from appliance.daemon import Daemon
from appliance.supervisor import ServiceState
from appliance.vehicle_io import link_summary
from drivers.actuators.messages import (
    BrakeCommand,
    SteeringCommand,
    SteeringMode,
    ThrottleCommand,
)
from tests.runtime.inline import inline_sim, isolated


async def wait_until(predicate: object, timeout_s: float = 5.0) -> None:
    assert callable(predicate)

    async def poll() -> None:
        while not predicate():
            await asyncio.sleep(0.01)

    await asyncio.wait_for(poll(), timeout_s)


async def test_board_inputs_stay_fresh_and_a_replugged_board_recovers() -> None:
    daemon = Daemon(inline_sim(isolated(load_config("sim"))))
    io = daemon.io
    assert io.boards is not None
    assert io.simulator is not None
    assert io.simulator.board_twins is not None
    board_twins = io.simulator.board_twins
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        loop = asyncio.get_running_loop()
        await wait_until(lambda: all(age < 0.1 for age in io.topics.ages_s(loop.time()).values()))
        assert set(io.topics.ages_s(0.0)) >= {"board.steering", "board.brake", "board.panel"}

        board_twins.brake.unplug()
        await wait_until(lambda: io.boards is not None and io.boards.brake.is_stale(loop.time()))
        assert daemon.supervisor.latched_error is None
        board_twins.brake.replug()
        await wait_until(
            lambda: io.boards is not None and not io.boards.brake.is_stale(loop.time())
        )
        health = io.boards.brake.health()
        assert health.reconnects >= 1
        assert health.connected
        record = daemon.supervisor.records["board.brake"]
        assert record.state is ServiceState.RUNNING  # the client reconnected by itself
    finally:
        daemon.request_stop("test over")
        result = await asyncio.wait_for(run, 3.0)
    assert result.exit_code == 0


async def test_shutdown_commands_the_boards_safe() -> None:
    daemon = Daemon(inline_sim(isolated(load_config("sim"))))
    boards = daemon.io.boards
    assert boards is not None
    result = await daemon.run(duration_s=1.0, handle_signals=False)
    assert result.exit_code == 0
    # The control loop commanded every board (the panel its lamps), and the safe-stop
    # frames went out on the wire while the links were still up.
    for client in (boards.throttle, boards.brake, boards.steering, boards.panel):
        assert client.health().commands_sent >= 1, client.board
    assert boards.brake.command == BrakeCommand(enable=True, position_pct=100.0)
    assert boards.throttle.command == ThrottleCommand(enable=False)
    assert boards.steering.command == SteeringCommand(SteeringMode.RELEASE)


async def test_simulated_scanners_see_the_launcher_ahead() -> None:
    daemon = Daemon(isolated(load_config("sim")))  # the simulated vehicle in its own process
    io = daemon.io
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        scan_left = io.topics.get("scan.left")
        first = await asyncio.wait_for(scan_left.wait_next(), 10.0)
        later = await asyncio.wait_for(scan_left.wait_next(first.seq + 10), 5.0)
        assert later.value.scan.scan_counter - first.value.scan.scan_counter >= 10
        points = later.value.points_vehicle_m()
        # The vehicle starts about 12.6 m behind the front board (x = 0 in the site),
        # heading 3 deg off its axis: the board's points lie ahead at x ~ 12.6 m.
        ahead = points[(abs(points[:, 1]) < 1.0)]
        assert len(ahead) > 5
        assert 12.0 < float(ahead[:, 0].min()) < 13.2
    finally:
        daemon.request_stop("test over")
        await asyncio.wait_for(run, 3.0)


async def test_scanner_refusing_its_configuration_is_given_up_without_a_loop() -> None:
    daemon = Daemon(inline_sim(isolated(load_config("sim"))))
    assert daemon.io.simulator is not None
    twin = daemon.io.simulator.scanner_twins["right"]
    twin.faults.fail_commands = {"mLMPsetscancfg": 0x5}  # invalid data
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        record = daemon.supervisor.records["lms111_right"]
        await wait_until(lambda: record.state is ServiceState.FAILED, 10.0)
        assert record.budget.total_restarts == 0
        assert "mLMPsetscancfg" in record.last_error
        assert daemon.supervisor.latched_error is None
        assert daemon.supervisor.records["lms111_left"].state is ServiceState.RUNNING
    finally:
        daemon.request_stop("test over")
        await asyncio.wait_for(run, 3.0)


async def test_pc104_faults_are_reported_and_survived_by_the_daemon() -> None:
    daemon = Daemon(inline_sim(isolated(load_config("sim"))))
    io = daemon.io
    assert io.simulator is not None
    assert io.pc104 is not None
    twin = io.simulator.pc104_twin
    assert twin is not None
    client = io.pc104
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        await wait_until(lambda: not client.health().stale)
        # The PC104 stops talking: stale within the age limit, the daemon keeps running.
        twin.faults.drop_all = True
        await wait_until(lambda: client.health().stale, 1.0)
        twin.faults.drop_all = False
        await wait_until(lambda: not client.health().stale)
        # Corrupted frames are counted, the link stays up.
        twin.faults.bad_crc = True
        await wait_until(lambda: client.health().crc_errors >= 5)
        twin.faults.bad_crc = False
        await wait_until(lambda: not client.health().stale)
        # A stuck counter is counted.
        twin.faults.stuck_counter = True
        await wait_until(lambda: client.health().counter_errors >= 3)
        twin.faults.stuck_counter = False
        # The cab operator takes over: the status says so.
        twin.faults.cab_control = True
        await wait_until(lambda: "control=cab" in link_summary(io)["pc104"])
        twin.faults.cab_control = False
        # The controller reboots: counters resync, the link comes back.
        twin.restart()
        await wait_until(lambda: not client.health().stale, 3.0)
        assert daemon.supervisor.latched_error is None
        assert daemon.supervisor.records["pc104"].budget.total_restarts == 0
    finally:
        daemon.request_stop("test over")
        result = await asyncio.wait_for(run, 3.0)
    assert result.exit_code == 0


async def test_scanners_set_to_cola_b_stream_too() -> None:
    config = isolated(load_config("sim"))  # the child process's twins speak CoLa-B too
    devices = config.devices.model_copy(
        update={
            side: getattr(config.devices, side).model_copy(
                update={"cola_dialect": ColaDialect.COLA_B}
            )
            for side in ("lms111_left", "lms111_right")
        }
    )
    daemon = Daemon(config.model_copy(update={"devices": devices}))
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        for side in ("left", "right"):
            first = await asyncio.wait_for(daemon.io.topics.get(f"scan.{side}").wait_next(), 10)
            assert first.value.scan.ranges_m.size == 541
            assert daemon.io.scanners[side].health.malformed_telegrams == 0
    finally:
        daemon.request_stop("test over")
        await asyncio.wait_for(run, 3.0)
