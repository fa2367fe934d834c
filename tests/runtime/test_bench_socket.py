"""The bench socket: framing, hostile input, and what it refuses to replace."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
from collections.abc import AsyncIterator
from pathlib import Path

import can
import pytest

from appliance.config import load_config
from appliance.control_client import ControlClient
from appliance.control_protocol import MAX_LINE_BYTES
from appliance.sim.bench import SimBench
from appliance.sim.bench_socket import BenchSocketError, serve_bench
from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.twins.pc104 import Pc104Twin
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld


@pytest.fixture
async def bench(tmp_path: Path) -> AsyncIterator[tuple[Path, SimBench]]:
    world = SimWorld(VehicleParams.from_config(load_config("sim")))
    boards = ActuatorTwins(world)
    pc104 = Pc104Twin(lambda: can.Bus(interface="virtual", channel="bench-socket"), world)
    path = tmp_path / "bench.sock"
    sim_bench = SimBench(world, boards, pc104, {})
    server = await serve_bench(path, sim_bench)
    try:
        yield path, sim_bench
    finally:
        server.close()
        await server.wait_closed()
        boards.close()


async def test_requests_and_replies_over_one_connection(bench: tuple[Path, SimBench]) -> None:
    path, sim_bench = bench
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    async with ControlClient(path) as client:
        assert await client.call({"op": "press", "button": "engage"}) == {"ok": True}
        reply = await client.call({"op": "press", "button": "launch"})
        assert reply["ok"] is False and "button" in reply["error"]
        state = (await client.call({"op": "observe"}))["state"]
    assert sim_bench.boards.panel.press_counts[0] == 1
    assert state["panel"]["plugged"] is True


async def test_garbage_gets_error_replies_and_an_endless_line_the_door(
    bench: tuple[Path, SimBench],
) -> None:
    path, _ = bench
    reader, writer = await asyncio.open_unix_connection(str(path))
    writer.write(b"not json\n\xff\xfe\n[1, 2]\n")
    for expected in ("not valid JSON", "not valid JSON", "JSON object"):
        reply = json.loads(await asyncio.wait_for(reader.readline(), 2.0))
        assert reply["ok"] is False and expected in reply["error"], reply
    writer.write(b"x" * (MAX_LINE_BYTES + 10))
    reply = json.loads(await asyncio.wait_for(reader.readline(), 2.0))
    assert "longer than" in reply["error"]
    assert await asyncio.wait_for(reader.read(), 2.0) == b""  # closed
    writer.close()
    # The bench still serves everyone else.
    async with ControlClient(path) as client:
        assert (await client.call({"op": "observe"}))["ok"]


async def test_a_stale_socket_is_replaced_and_anything_else_refused(tmp_path: Path) -> None:
    world = SimWorld(VehicleParams.from_config(load_config("sim")))
    boards = ActuatorTwins(world)
    sim_bench = SimBench(world, boards, None, {})
    try:
        stale = tmp_path / "stale.sock"
        leftover = socket.socket(socket.AF_UNIX)
        leftover.bind(str(stale))  # what a killed simulator leaves behind
        leftover.close()
        server = await serve_bench(stale, sim_bench)
        server.close()
        await server.wait_closed()
        precious = tmp_path / "notes.txt"
        precious.write_text("keep me")
        with pytest.raises(BenchSocketError, match="not a socket"):
            await serve_bench(precious, sim_bench)
        assert precious.read_text() == "keep me"
    finally:
        boards.close()
