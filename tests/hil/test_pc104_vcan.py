"""The PC104 link over real SocketCAN: the twin in its own process, the client here.

Run through ``tools/vcan_run.py`` (user-mode Linux when the host has no CAN). What this
covers that the in-process tests cannot: the socketcan backend with kernel filters and
the event-loop reader, a peer in another process, can-utils as an independent witness
(``candump -L`` records the traffic and the log is checked with cantools and an
independent CRC-8, not with the client's code), frames injected with ``cansend`` (a wrong
length, a bad CRC), and the interface going down and up under a running client.
"""

from __future__ import annotations

import asyncio
import itertools
import re
import shutil
import signal
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import cantools
import pytest

from appliance.config import load_config, parts
from appliance.config.models import CanEndpoint, VehicleConfig
from drivers.pc104 import protocol
from drivers.pc104.client import Pc104Client
from drivers.pc104.endpoint import CanInterface
from drivers.pc104.messages import (
    ControlSource,
    HlExpectedPose,
    HlPose,
    MotionCommand,
    MotionPattern,
    Pc104Status,
    PoseState,
    SteeringLoop,
)

pytestmark = pytest.mark.vcan

PROJECT_ROOT = Path(__file__).resolve().parents[2]
FORWARD = MotionCommand(MotionPattern.STRAIGHT, 0.8)
_LOG_LINE = re.compile(r"^\((?P<ts>\d+\.\d+)\) \S+ (?P<id>[0-9A-F]{3})#(?P<data>(?:[0-9A-F]{2})*)$")


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} not found on PATH: apt-get install can-utils iproute2", pytrace=False)
    return path


def crc8_sae_j1850_bitwise(data: bytes) -> int:
    """An independent, bit-by-bit CRC-8 SAE J1850 (poly 0x1D, init 0xFF, xorout 0xFF)."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


async def run_tool(*argv: str) -> None:
    proc = await asyncio.create_subprocess_exec(
        *argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    out, _ = await asyncio.wait_for(proc.communicate(), 10.0)
    assert proc.returncode == 0, f"{argv}: {out.decode(errors='replace')}"


async def wait_until(
    condition: Callable[[], bool], timeout_s: float, what: str, detail: Callable[[], str]
) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}; {detail()}")
        await asyncio.sleep(0.01)


async def drive_until_moving(client: Pc104Client, detail: Callable[[], str]) -> None:
    """Play the control loop until the twin's vehicle moves. If a scheduling hiccup of
    the (user-mode Linux) machine made the status stale, the client holds STOP; re-arm
    with STOP as the mode machine would, rather than fail on the machine's jitter."""
    deadline = time.monotonic() + 5.0
    while True:
        status = client.topics.status.latest()
        if status is not None and status.value.measured_speed_mps > 0.1:
            assert status.value.active_pattern is MotionPattern.STRAIGHT, detail()
            assert status.value.control_source is ControlSource.AUTOMATIC, detail()
            return
        if time.monotonic() > deadline:
            pytest.fail(f"the vehicle did not move; {detail()}")
        holding = client.health().holding_stop
        client.send_command(MotionCommand.stop() if holding else FORWARD)
        # Every frame of the contract goes on the bus: the pose frames too, with the
        # set-points still the HL's (a PC104 following them ignores the poses).
        client.send_pose(POSE, EXPECTED)
        await asyncio.sleep(0.01)


POSE = HlPose(-20.0, 0.1, 0.0, PoseState.OK)
EXPECTED = HlExpectedPose(-6.0, 0.0, 0.0, SteeringLoop.HL)


def vcan_config(channel: str) -> VehicleConfig:
    config = load_config("sim")
    endpoint = CanEndpoint(interface=CanInterface.SOCKETCAN, channel=channel)
    return config.model_copy(
        update={"devices": config.devices.model_copy(update={"can": endpoint})}
    )


def check_candump_log(path: Path, injected: set[tuple[int, bytes]]) -> dict[int, int]:
    """Check every frame of the contract in a ``candump -L`` log with cantools and an
    independent CRC; returns the number of frames per identifier."""
    db = cantools.database.load_file(str(protocol.DBC_PATH))
    assert isinstance(db, cantools.database.can.Database)
    by_id: dict[int, list[tuple[float, bytes]]] = defaultdict(list)
    for line in path.read_text().splitlines():
        match = _LOG_LINE.match(line)
        assert match is not None, f"unexpected candump line {line!r}"
        frame = (int(match["id"], 16), bytes.fromhex(match["data"]))
        if frame in injected:
            injected.discard(frame)
            continue
        by_id[frame[0]].append((float(match["ts"]), frame[1]))
    assert not injected, f"candump did not see the injected frames {injected}"
    assert set(by_id) == {m.frame_id for m in db.messages}, sorted(map(hex, by_id))
    for frame_id, frames in by_id.items():
        message = db.get_message_by_frame_id(frame_id)
        counters = []
        for _, data in frames:
            assert len(data) == message.length, (message.name, data.hex())
            crc_input = frame_id.to_bytes(2, "big") + data[:-1]
            assert data[-1] == crc8_sae_j1850_bitwise(crc_input), (message.name, data.hex())
            values = message.decode_simple(data, decode_choices=False)
            counters.append(int(values["Counter"]))  # type: ignore[arg-type]
        steps = {(b - a) % 16 for a, b in itertools.pairwise(counters)}
        assert steps == {1}, f"{message.name}: counter steps {steps}"
        period_s = statistics.median(b[0] - a[0] for a, b in itertools.pairwise(frames))
        assert message.cycle_time is not None
        # Never faster than the contract; slower only by what a user-mode Linux guest on a
        # loaded host loses to scheduling (senders skip missed periods instead of bursting).
        nominal_s = message.cycle_time / 1000
        assert 0.8 * nominal_s <= period_s <= 2.5 * nominal_s, (message.name, period_s)
    command = db.get_message_by_frame_id(0x100)
    patterns = {str(command.decode_simple(d)["MotionPattern"]) for _, d in by_id[0x100]}
    assert "STRAIGHT" in patterns
    return {frame_id: len(frames) for frame_id, frames in by_id.items()}


@pytest.mark.timeout(90)
async def test_client_and_twin_process_over_vcan(vcan_channel: str, tmp_path: Path) -> None:
    dump_path, twin_log = tmp_path / "candump.log", tmp_path / "twin.log"
    with dump_path.open("w") as dump_out:
        candump = await asyncio.create_subprocess_exec(
            _tool("candump"), "-L", vcan_channel, stdout=dump_out
        )
    with twin_log.open("w") as twin_err:
        twin = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "appliance.sim.twins.pc104",
            "--channel",
            vcan_channel,
            cwd=PROJECT_ROOT,
            stdout=subprocess.DEVNULL,
            stderr=twin_err,
        )
    config = vcan_config(vcan_channel)
    client = Pc104Client(parts.pc104_client_params(config), config.devices.can)
    runner = asyncio.create_task(client.run(lambda: None))

    def detail() -> str:
        return f"client: {client.health()}; twin log tail: {twin_log.read_text()[-1500:]}"

    try:
        await wait_until(lambda: client.health().peer_ready, 40.0, "the twin process ready", detail)
        await drive_until_moving(client, detail)
        client.send_command(MotionCommand.stop())

        # A frame of the status identifier with the wrong length, and one with a bad CRC.
        status_id = protocol.spec_for(Pc104Status).frame_id
        _, good = protocol.encode(Pc104Status(MotionPattern.STOP, False, ControlSource.CAB), 3)
        bad_crc = good[:-1] + bytes([good[-1] ^ 0x5A])
        injected = {(status_id, b"\x01\x02"), (status_id, bad_crc)}
        for frame_id, data in sorted(injected):
            await run_tool(_tool("cansend"), vcan_channel, f"{frame_id:03X}#{data.hex().upper()}")
        await wait_until(lambda: client.health().crc_errors == 1, 10.0, "the bad CRC", detail)
        await asyncio.sleep(0.1)
        health = client.health()
        assert (health.malformed_frames, health.crc_errors) == (1, 1), detail()
        assert health.connected and health.reconnects == 0, detail()
        assert health.counter_errors == 0 and health.send_drops == 0
        await asyncio.sleep(0.2)
        candump.send_signal(signal.SIGINT)
        await asyncio.wait_for(candump.wait(), 5.0)
        counts = check_candump_log(dump_path, injected)
        assert counts[status_id] >= 40

        # The interface goes down and comes back: the client reopens and status flows.
        await run_tool(_tool("ip"), "link", "set", vcan_channel, "down")
        await wait_until(lambda: client.health().stale, 2.0, "stale status while down", detail)
        await asyncio.sleep(0.3)
        await run_tool(_tool("ip"), "link", "set", vcan_channel, "up")
        await wait_until(
            lambda: client.health().connected and not client.health().stale,
            15.0,
            "status flowing again after the interface came back",
            detail,
        )
        assert client.health().reconnects >= 1
        assert twin.returncode is None, "the twin process died"
    finally:
        await run_tool(_tool("ip"), "link", "set", vcan_channel, "up")  # for the next test
        runner.cancel()
        await asyncio.gather(runner, return_exceptions=True)
        for proc in (candump, twin):
            if proc.returncode is None:
                proc.terminate()
            try:
                await asyncio.wait_for(proc.wait(), 5.0)
            except TimeoutError:
                proc.kill()
                await proc.wait()
    assert twin.returncode == 0, twin_log.read_text()[-2000:]
