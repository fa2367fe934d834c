"""Board clients against the twins over real pseudo-terminals, in one process, in real time.

Each test runs the four twins, the simulated world and the four clients as tasks, and then
breaks something the way the vehicle would: a stalled board, a pulled USB cable, line
noise, a host that stops commanding, an operator's foot, a quick thumb on the panel.
"""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import pytest
from structlog.testing import capture_logs

from appliance.board_clients import BoardClients, make_board_clients
from appliance.config import load_config
from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.actuators.client import ActuatorClient
from drivers.actuators.messages import (
    BoardKind,
    BoardStatus,
    BrakeCommand,
    BrakeTelemetry,
    Buttons,
    FaultCode,
    Lamps,
    PanelCommand,
    PanelTelemetry,
    SteeringCommand,
    SteeringMode,
    SteeringTelemetry,
    ThrottleCommand,
)

CONFIG = load_config("sim")
TIMEOUT_S = CONFIG.safety.lower_layer_command_timeout_s


@dataclass
class Rig:
    world: SimWorld
    twins: ActuatorTwins
    clients: BoardClients
    beats: dict[BoardKind, int] = field(default_factory=lambda: dict.fromkeys(BoardKind, 0))

    def beat_for(self, board: BoardKind) -> Callable[[], None]:
        def beat() -> None:
            self.beats[board] += 1

        return beat


async def wait_until(predicate: Callable[[], bool], timeout_s: float = 3.0) -> float:
    """Poll every millisecond; return the monotonic time the predicate became true."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.001)
    return time.monotonic()


def latest(client: ActuatorClient[Any]) -> Any:
    sample = client.telemetry.latest()
    assert sample is not None
    return sample.value


@pytest.fixture
async def rig() -> AsyncIterator[Rig]:
    world = SimWorld(VehicleParams.from_config(CONFIG))
    twins = ActuatorTwins.from_config(CONFIG, world)
    rig = Rig(world, twins, make_board_clients(CONFIG, twins.port_path))
    tasks = [asyncio.create_task(twins.run()), asyncio.create_task(world.run_realtime())]
    tasks += [asyncio.create_task(c.run(rig.beat_for(c.board))) for c in rig.clients.all()]
    try:
        await wait_until(lambda: all(c.health().healthy for c in rig.clients.all()))
        yield rig
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        twins.close()


async def release_all(rig: Rig) -> None:
    """Hand every board back to the operator, which also clears the power-on latch."""
    c = rig.clients
    c.steering.set_command(SteeringCommand(SteeringMode.RELEASE))
    c.throttle.set_command(ThrottleCommand(False))
    c.brake.set_command(BrakeCommand(False))
    await wait_until(
        lambda: all(
            not latest(x).status & BoardStatus.LATCHED for x in (c.steering, c.throttle, c.brake)
        )
    )


async def test_telemetry_flows_at_100_hz_on_every_board(rig: Rig) -> None:
    start = {c.board: c.telemetry.latest() for c in rig.clients.all()}
    beats_before = dict(rig.beats)
    await asyncio.sleep(1.2)
    for client in rig.clients.all():
        first, last = start[client.board], client.telemetry.latest()
        assert first is not None and last is not None
        rate_hz = (last.seq - first.seq) / (last.stamp_s - first.stamp_s)
        assert 90.0 <= rate_hz <= 110.0, (client.board, rate_hz)
        health = client.health()
        assert 90.0 <= health.frames_per_s <= 110.0
        assert health.crc_errors == health.framing_errors == health.seq_gaps == 0
        assert rig.beats[client.board] - beats_before[client.board] >= 50


async def test_commands_move_the_twins_and_the_world(rig: Rig) -> None:
    await release_all(rig)
    c = rig.clients
    c.steering.set_command(SteeringCommand(SteeringMode.POSITION, 2.0))
    c.throttle.set_command(ThrottleCommand(True, 30.0))
    await wait_until(lambda: abs(latest(c.steering).servo_position_rad - 2.0) < 0.02)
    await wait_until(lambda: abs(latest(c.throttle).actuator_position_pct - 30.0) < 0.5)
    assert latest(c.steering).status & BoardStatus.ENGAGED
    assert rig.world.command.front_steer_rad == pytest.approx(
        rig.twins.steering.wheel_angle_rad / rig.twins.steering.params.steering_ratio
    )
    assert rig.world.command.throttle_pct == pytest.approx(30.0, abs=0.5)
    c.throttle.set_command(ThrottleCommand(False))
    c.brake.set_command(BrakeCommand(True, 60.0))
    await wait_until(lambda: latest(c.brake).actuator_position_pct > 59.5)
    assert rig.world.command.brake_pct == pytest.approx(60.0, abs=0.5)
    echo = latest(c.brake).command_seq_echo
    await asyncio.sleep(0.1)  # the command is re-sent at 50 Hz: the board sees it again
    assert latest(c.brake).command_seq_echo != echo


async def test_a_stalled_board_is_stale_within_its_age_limit(rig: Rig) -> None:
    steering = rig.clients.steering
    with capture_logs() as logs:
        rig.twins.steering.stall()
        detected_s = await wait_until(lambda: steering.stale_episodes == 1)
        last = steering.telemetry.latest()
        assert last is not None
        assert steering.max_age_s <= detected_s - last.stamp_s <= steering.max_age_s + 0.015
        beats = rig.beats[BoardKind.STEERING]
        await asyncio.sleep(0.1)
        assert rig.beats[BoardKind.STEERING] == beats  # no heartbeat while stale
        rig.twins.steering.stall(False)
        await wait_until(lambda: steering.health().healthy)
    events = [e["event"] for e in logs if e.get("board") == "steering"]
    assert events == ["telemetry_stale", "telemetry_fresh"]


async def test_unplug_and_replug_recover_with_one_log_per_episode(rig: Rig) -> None:
    throttle, twin = rig.clients.throttle, rig.twins.throttle
    await release_all(rig)
    throttle.set_command(ThrottleCommand(True, 20.0))
    await wait_until(lambda: twin.actuator_position_pct > 19.0)
    with capture_logs() as logs:
        twin.unplug()
        await wait_until(lambda: not throttle.connected)
        beats = rig.beats[BoardKind.THROTTLE]
        await asyncio.sleep(0.4)  # several reopen attempts fail meanwhile
        assert rig.beats[BoardKind.THROTTLE] == beats
        assert throttle.health().stale
        assert twin.latched and twin.actuator_position_pct < 1.0  # the board timed out alone
        received = twin.commands_received
        twin.replug()
        await wait_until(lambda: throttle.health().healthy)
        await wait_until(lambda: twin.commands_received > received)  # current command re-sent
    warnings = [e for e in logs if e.get("board") == "throttle" and e["log_level"] == "warning"]
    assert [e["event"] for e in warnings] == ["link_lost"]
    assert [e["event"] for e in logs if e["event"] == "link_restored"] == ["link_restored"]
    assert throttle.health().reconnects == 1
    # The re-sent engage command is refused by the latch until the host releases again.
    assert latest(throttle).status & BoardStatus.LATCHED
    assert latest(throttle).fault is FaultCode.COMMAND_TIMEOUT
    throttle.set_command(ThrottleCommand(False))
    await wait_until(lambda: not latest(throttle).status & BoardStatus.LATCHED)
    throttle.set_command(ThrottleCommand(True, 20.0))
    await wait_until(lambda: twin.actuator_position_pct > 19.0)


async def test_noise_and_bad_crc_are_counted_and_survived(rig: Rig) -> None:
    brake = rig.clients.brake
    before = brake.telemetry.latest()
    assert before is not None
    rig.twins.brake.inject_noise(random.Random(7).randbytes(400))
    await asyncio.sleep(0.05)
    noise_health = brake.health()
    rig.twins.brake.corrupt_next_frames(5)
    await asyncio.sleep(0.3)
    health = brake.health()
    assert health.crc_errors - noise_health.crc_errors == 5
    assert noise_health.framing_errors + noise_health.crc_errors + noise_health.resyncs > 0
    assert health.healthy
    after = brake.telemetry.latest()
    assert after is not None and after.seq - before.seq >= 20


async def test_board_timeout_applies_the_safe_defaults(rig: Rig) -> None:
    c, world = rig.clients, rig.world
    await release_all(rig)
    c.steering.set_command(SteeringCommand(SteeringMode.POSITION, 1.0))
    c.throttle.set_command(ThrottleCommand(True, 30.0))
    await wait_until(lambda: world.command.throttle_pct > 29.0 and world.command.brake_pct < 1.0)
    await wait_until(lambda: latest(c.steering).status & BoardStatus.ENGAGED)
    for client in c.all():
        client.clear_command()
    stopped_s = time.monotonic()
    latched_s = await wait_until(lambda: bool(latest(c.throttle).status & BoardStatus.LATCHED))
    assert latched_s - stopped_s <= TIMEOUT_S + 0.05
    await wait_until(lambda: latest(c.throttle).actuator_position_pct < 0.5)
    await wait_until(lambda: latest(c.brake).actuator_position_pct > 49.0)
    steering = latest(c.steering)
    assert steering.status & BoardStatus.LATCHED and not steering.status & BoardStatus.ENGAGED
    assert steering.motor_torque_nm == 0.0 and rig.twins.steering.servo.torque_nm == 0.0
    assert latest(c.brake).fault is FaultCode.COMMAND_TIMEOUT
    assert world.command.throttle_pct < 0.5 and world.command.brake_pct > 49.0
    await wait_until(lambda: latest(c.panel).fault is FaultCode.COMMAND_TIMEOUT)
    assert rig.twins.panel.lamps == Lamps.OVERRIDE | Lamps.WARNING


async def test_an_operator_brake_tap_is_visible_in_brake_telemetry(rig: Rig) -> None:
    brake = rig.clients.brake
    await release_all(rig)
    await wait_until(lambda: latest(brake).actuator_position_pct < 0.5)
    seen: list[BrakeTelemetry] = []

    async def collect() -> None:
        seq = 0
        while True:
            sample = await brake.telemetry.wait_next(seq)
            seq = sample.seq
            seen.append(sample.value)

    collector = asyncio.create_task(collect())
    rig.twins.brake.operator_brake_tap(40.0, 0.15)
    await wait_until(lambda: rig.world.command.brake_pct > 39.0)
    await asyncio.sleep(0.3)
    collector.cancel()
    tapped = [s for s in seen if s.status & BoardStatus.OPERATOR_OVERRIDE]
    assert len(tapped) >= 10
    assert all(s.pedal_position_pct == pytest.approx(40.0) for s in tapped)
    assert all(s.actuator_position_pct < 0.5 for s in tapped)  # the board did not brake
    assert seen[-1].pedal_position_pct is not None and seen[-1].pedal_position_pct < 0.5


async def test_panel_presses_are_never_lost(rig: Rig) -> None:
    panel, twin = rig.clients.panel, rig.twins.panel
    first: PanelTelemetry = latest(panel)
    for _ in range(7):  # faster than the 10 ms telemetry period
        twin.press("engage")
        await asyncio.sleep(0.002)
    for _ in range(3):
        twin.press(Buttons.SPEED_PLUS)  # three presses between two frames
    twin.hold("speed_minus", 0.3)
    await wait_until(lambda: bool(latest(panel).buttons_down & Buttons.SPEED_MINUS))
    await wait_until(lambda: not latest(panel).buttons_down & Buttons.SPEED_MINUS)
    last: PanelTelemetry = latest(panel)

    def presses(button: Buttons) -> int:
        return (last.press_count(button) - first.press_count(button)) & 0xFF

    assert presses(Buttons.ENGAGE) == 7
    assert presses(Buttons.SPEED_PLUS) == 3
    assert presses(Buttons.SPEED_MINUS) == 1
    panel.set_command(PanelCommand(Lamps.WARNING, "CHECK BRAKE"))
    await wait_until(lambda: twin.lamps == Lamps.WARNING and twin.display_text == "CHECK BRAKE")


async def test_estop_is_reported_everywhere_and_a_twist_does_not_re_engage(rig: Rig) -> None:
    c = rig.clients
    await release_all(rig)
    c.throttle.set_command(ThrottleCommand(True, 20.0))
    await wait_until(lambda: latest(c.throttle).actuator_position_pct > 19.0)
    rig.twins.panel.estop(True)
    await wait_until(lambda: bool(latest(c.panel).buttons_down & Buttons.ESTOP))

    def all_report_estop() -> bool:
        return all(latest(x).fault is FaultCode.ESTOP for x in (c.steering, c.throttle, c.brake))

    await wait_until(all_report_estop)
    await wait_until(lambda: latest(c.brake).actuator_position_pct > 99.0)
    await wait_until(lambda: latest(c.throttle).actuator_position_pct < 0.5)
    rig.twins.panel.estop(False)
    await asyncio.sleep(0.2)
    # The host still asks for 20 % throttle: refused until it releases and re-engages.
    assert latest(c.throttle).status & BoardStatus.LATCHED
    assert latest(c.throttle).actuator_position_pct < 0.5
    # The brake host sends "release" (manual driving): the pedal is the operator's again.
    await wait_until(lambda: latest(c.brake).actuator_position_pct < 0.5)
    assert latest(c.panel).press_count(Buttons.ESTOP) == 1


async def test_a_port_is_exclusive(rig: Rig) -> None:
    second = ActuatorClient(BrakeTelemetry, rig.twins.port_path("sim://brake"))
    task = asyncio.create_task(second.run(lambda: None))
    try:
        await wait_until(lambda: "lock" in second.last_error)
        assert not second.connected
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_the_wrong_board_on_a_port_is_refused() -> None:
    """A swapped cable: the steering client must never take brake telemetry for its own."""
    twins = ActuatorTwins()
    crossed = ActuatorClient(SteeringTelemetry, twins.port_path("sim://brake"))
    tasks = [asyncio.create_task(twins.run()), asyncio.create_task(crossed.run(lambda: None))]
    try:
        await wait_until(lambda: crossed.wrong_board_frames > 10)
        assert crossed.telemetry.latest() is None
        assert crossed.health().stale and "BrakeTelemetry" in crossed.health().last_error
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        twins.close()
