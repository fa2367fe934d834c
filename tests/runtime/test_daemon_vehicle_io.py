"""The daemon on the built-in simulated vehicle: its drivers talk to the twins for real."""

from __future__ import annotations

import asyncio

from appliance.config import load_config
from appliance.daemon import Daemon
from appliance.supervisor import ServiceState


async def wait_until(predicate: object, timeout_s: float = 5.0) -> None:
    assert callable(predicate)

    async def poll() -> None:
        while not predicate():
            await asyncio.sleep(0.01)

    await asyncio.wait_for(poll(), timeout_s)


async def test_board_inputs_stay_fresh_and_a_replugged_board_recovers() -> None:
    daemon = Daemon(load_config("sim"))
    io = daemon.io
    assert io.boards is not None
    assert io.board_twins is not None
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        loop = asyncio.get_running_loop()
        await wait_until(lambda: all(age < 0.1 for age in io.topics.ages_s(loop.time()).values()))
        assert set(io.topics.ages_s(0.0)) >= {"board.steering", "board.brake", "board.panel"}

        io.board_twins.brake.unplug()
        await wait_until(lambda: io.boards is not None and io.boards.brake.is_stale(loop.time()))
        assert daemon.supervisor.latched_error is None
        io.board_twins.brake.replug()
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
    daemon = Daemon(load_config("sim"))
    boards = daemon.io.boards
    assert boards is not None
    result = await daemon.run(duration_s=1.0, handle_signals=False)
    assert result.exit_code == 0
    # Nothing was engaged, so nothing was commanded before the shutdown; the safe-stop
    # frames went out on the wire while the links were still up.
    for client in (boards.throttle, boards.brake, boards.steering):
        assert client.health().commands_sent >= 1, client.board
    assert boards.panel.health().commands_sent == 0
