"""The boards' rules, stepped with explicit time over a real pty (no asyncio, no clock)."""

from __future__ import annotations

import contextlib
import errno
import os
import select
from collections.abc import Iterator

import pytest

from appliance.config import load_config
from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.twins.boards import HOST_LOST_TEXT
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.actuators.framing import ActuatorProtocolError
from drivers.actuators.messages import (
    BoardStatus,
    BrakeCommand,
    BrakeTelemetry,
    Buttons,
    Command,
    FaultCode,
    Lamps,
    PanelCommand,
    PanelTelemetry,
    SteeringCommand,
    SteeringMode,
    SteeringTelemetry,
    Telemetry,
    ThrottleCommand,
    ThrottleTelemetry,
)
from drivers.actuators.protocol import NEED_DATA, ActuatorCodec, Role


class Host:
    """The host end of one link, without a client: raw fd plus codec."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self.codec = ActuatorCodec(Role.HOST)
        self.errors = 0

    def send(self, command: Command) -> None:
        os.write(self.fd, self.codec.encode(command))

    def receive(self) -> list[Telemetry]:
        # The kernel moves pty bytes asynchronously: read until the line has been quiet a bit.
        while select.select([self.fd], [], [], 0.01)[0]:
            with contextlib.suppress(BlockingIOError):
                data = os.read(self.fd, 65536)
                if not data:
                    break
                self.codec.receive_data(data)
        events: list[Telemetry] = []
        while True:
            try:
                event = self.codec.next_event()
            except ActuatorProtocolError:
                self.errors += 1
                continue
            if event is NEED_DATA:
                return events
            if not isinstance(
                event, SteeringTelemetry | ThrottleTelemetry | BrakeTelemetry | PanelTelemetry
            ):
                raise AssertionError(f"a board sent a command: {event}")
            events.append(event)

    def close(self) -> None:
        os.close(self.fd)


@pytest.fixture
def world() -> SimWorld:
    return SimWorld(VehicleParams.from_config(load_config("sim")))


@pytest.fixture
def twins(world: SimWorld) -> Iterator[ActuatorTwins]:
    rig = ActuatorTwins(world)
    yield rig
    rig.close()


def host_for(twins: ActuatorTwins, name: str) -> Host:
    return Host(twins.port_path(f"sim://{name}"))


def step_for(
    twins: ActuatorTwins,
    start_s: float,
    seconds: float,
    host: Host | None = None,
    command: Command | None = None,
) -> float:
    """Step all boards at 100 Hz, optionally sending ``command`` every other step (50 Hz)."""
    t = start_s
    for i in range(round(seconds / 0.01)):
        if host is not None and command is not None and i % 2 == 0:
            host.send(command)
        t = start_s + (i + 1) * 0.01
        twins.step(t)
    return t


def test_port_paths(twins: ActuatorTwins) -> None:
    assert os.path.realpath(twins.port_path("sim://brake")).startswith("/dev/pts/")
    with pytest.raises(ValueError, match="no simulated board"):
        twins.port_path("sim://wiper")


def test_power_on_is_a_latched_safe_default(twins: ActuatorTwins, world: SimWorld) -> None:
    brake = host_for(twins, "brake")
    step_for(twins, 0.0, 1.0)
    last = brake.receive()[-1]
    assert isinstance(last, BrakeTelemetry)
    assert last.status & BoardStatus.LATCHED and last.fault is FaultCode.COMMAND_TIMEOUT
    assert last.actuator_position_pct == pytest.approx(twins.brake.timeout_brake_pct, abs=0.5)
    assert world.command.brake_pct == pytest.approx(50.0, abs=0.5)
    brake.close()


def test_engaging_needs_a_release_first(twins: ActuatorTwins) -> None:
    throttle = host_for(twins, "throttle")
    t = step_for(twins, 0.0, 0.3, throttle, ThrottleCommand(True, 30.0))
    assert twins.throttle.actuator_position_pct == 0.0
    assert twins.throttle.commands_ignored > 0
    t = step_for(twins, t, 0.05, throttle, ThrottleCommand(False))
    t = step_for(twins, t, 1.0, throttle, ThrottleCommand(True, 30.0))
    assert twins.throttle.actuator_position_pct == pytest.approx(30.0, abs=0.5)
    last = throttle.receive()[-1]
    assert last.status & BoardStatus.ENGAGED and not last.status & BoardStatus.LATCHED
    assert last.command_seq_echo == (throttle.codec.next_tx_seq - 1) & 0xFF
    throttle.close()


def test_command_timeout_goes_to_the_safe_default(twins: ActuatorTwins, world: SimWorld) -> None:
    hosts = {name: host_for(twins, name) for name in ("steering", "throttle", "brake")}
    engage: dict[str, tuple[Command, Command]] = {
        "steering": (
            SteeringCommand(SteeringMode.RELEASE),
            SteeringCommand(SteeringMode.POSITION, 2.0),
        ),
        "throttle": (ThrottleCommand(False), ThrottleCommand(True, 30.0)),
        "brake": (BrakeCommand(False), BrakeCommand(True, 10.0)),
    }
    t = 0.0
    for phase in (0, 1):
        for i in range(100 if phase else 5):
            if i % 2 == 0:
                for name, host in hosts.items():
                    host.send(engage[name][phase])
            t += 0.01
            twins.step(t)
    assert twins.throttle.actuator_position_pct > 25.0
    assert twins.steering.wheel_angle_rad > 1.5
    last_command_s = t - 0.01
    while not twins.throttle.latched:  # nobody sends any more
        t += 0.01
        twins.step(t)
    assert t - last_command_s == pytest.approx(0.11, abs=0.015)
    t = step_for(twins, t, 1.0)
    assert twins.throttle.actuator_position_pct < 0.5
    assert twins.brake.actuator_position_pct == pytest.approx(50.0, abs=0.5)
    assert twins.steering.servo.torque_nm == 0.0 and twins.steering.latched
    assert world.command.throttle_pct < 0.5
    for host in hosts.values():
        host.close()


def test_estop_applies_full_brake_and_stays_latched(twins: ActuatorTwins) -> None:
    brake = host_for(twins, "brake")
    t = step_for(twins, 0.0, 0.3, brake, BrakeCommand(False))
    assert twins.brake.actuator_position_pct < 1.0
    twins.panel.estop(True)
    t = step_for(twins, t, 1.0, brake, BrakeCommand(False))
    last = brake.receive()[-1]
    assert last.status & BoardStatus.ESTOP and last.fault is FaultCode.ESTOP
    assert twins.brake.actuator_position_pct == pytest.approx(100.0, abs=0.5)
    twins.panel.estop(False)
    t = step_for(twins, t, 0.05)
    assert twins.brake.latched and not twins.brake.estop_active
    t = step_for(twins, t, 1.0, brake, BrakeCommand(False))
    assert not twins.brake.latched and twins.brake.actuator_position_pct < 1.0
    brake.close()


def test_panel_counts_every_press_and_records_lamps(twins: ActuatorTwins) -> None:
    panel = host_for(twins, "panel")
    t = step_for(twins, 0.0, 0.05)
    assert twins.panel.lamps == Lamps.OVERRIDE | Lamps.WARNING
    assert twins.panel.display_text == HOST_LOST_TEXT
    for _ in range(3):
        twins.panel.press("engage")  # three presses between two telemetry frames
    twins.panel.hold(Buttons.SPEED_PLUS, 0.1)
    t = step_for(twins, t, 0.05, panel, PanelCommand(Lamps.ENGAGED, "AUTO"))
    frames = panel.receive()
    last = frames[-1]
    assert isinstance(last, PanelTelemetry)
    assert last.press_count(Buttons.ENGAGE) == 3
    assert last.buttons_down == Buttons.SPEED_PLUS
    t = step_for(twins, t, 0.2, panel, PanelCommand(Lamps.ENGAGED, "AUTO"))
    last = panel.receive()[-1]
    assert isinstance(last, PanelTelemetry)
    assert last.buttons_down == Buttons.NONE and last.press_count(Buttons.SPEED_PLUS) == 1
    assert twins.panel.lamps == Lamps.ENGAGED and twins.panel.display_text == "AUTO"
    step_for(twins, t, 0.3)
    assert twins.panel.lamp_log[-1][1:] == (Lamps.OVERRIDE | Lamps.WARNING, HOST_LOST_TEXT)
    with pytest.raises(ValueError, match="unknown button"):
        twins.panel.press("horn")
    panel.close()


def test_brake_tap_shows_in_the_pedal_and_the_world(twins: ActuatorTwins, world: SimWorld) -> None:
    brake = host_for(twins, "brake")
    t = step_for(twins, 0.0, 0.5, brake, BrakeCommand(False))
    brake.receive()
    twins.brake.operator_brake_tap(40.0, 0.1)
    t = step_for(twins, t, 0.05, brake, BrakeCommand(False))
    assert world.command.brake_pct == pytest.approx(40.0)
    during = brake.receive()[-1]
    assert isinstance(during, BrakeTelemetry)
    assert during.pedal_position_pct == pytest.approx(40.0)
    assert during.actuator_position_pct < 1.0
    assert during.status & BoardStatus.OPERATOR_OVERRIDE
    step_for(twins, t, 0.2, brake, BrakeCommand(False))
    after = brake.receive()[-1]
    assert isinstance(after, BrakeTelemetry)
    assert after.pedal_position_pct is not None and after.pedal_position_pct < 1.0
    assert world.command.brake_pct < 1.0
    brake.close()


def test_steering_moves_the_world_and_the_pot(twins: ActuatorTwins, world: SimWorld) -> None:
    steering = host_for(twins, "steering")
    t = step_for(twins, 0.0, 0.05, steering, SteeringCommand(SteeringMode.RELEASE))
    step_for(twins, t, 1.5, steering, SteeringCommand(SteeringMode.POSITION, 3.0))
    wheel = twins.steering.wheel_angle_rad
    assert wheel == pytest.approx(3.0 - twins.steering.params.backlash_rad / 2, abs=0.02)
    assert world.command.front_steer_rad == pytest.approx(wheel / 18.0)
    last = steering.receive()[-1]
    assert isinstance(last, SteeringTelemetry)
    assert last.servo_position_rad == pytest.approx(3.0, abs=0.011)
    ideal = twins.steering.pot_mapping.ideal_counts(wheel)
    assert abs(last.pot_raw_counts - ideal) <= 4
    steering.close()


def test_torque_loss_raises_a_position_error(twins: ActuatorTwins) -> None:
    steering = host_for(twins, "steering")
    twins.steering.inject_torque_loss(0.0)
    t = step_for(twins, 0.0, 0.05, steering, SteeringCommand(SteeringMode.RELEASE))
    step_for(twins, t, 1.0, steering, SteeringCommand(SteeringMode.POSITION, 2.0))
    last = steering.receive()[-1]
    assert isinstance(last, SteeringTelemetry)
    assert twins.steering.wheel_angle_rad == 0.0
    assert last.fault is FaultCode.POSITION_ERROR and last.status & BoardStatus.FAULT
    assert last.supply_voltage_v == 0.0
    steering.close()


def test_fault_injection_on_the_wire(twins: ActuatorTwins) -> None:
    brake = host_for(twins, "brake")
    twins.brake.corrupt_next_frames(3)
    t = step_for(twins, 0.0, 0.1)
    assert len(brake.receive()) == 10 - 3
    assert brake.codec.framing_stats.crc_errors == 3
    twins.brake.stall()
    t = step_for(twins, t, 0.1)
    assert brake.receive() == []
    twins.brake.stall(False)
    twins.brake.inject_noise(bytes(range(256)))
    step_for(twins, t, 0.1)
    assert len(brake.receive()) >= 9
    brake.close()


def test_unplug_is_a_real_hangup(twins: ActuatorTwins) -> None:
    path = twins.port_path("sim://throttle")
    host = Host(path)
    twins.throttle.unplug()
    assert not os.path.exists(path)
    assert os.read(host.fd, 100) == b""  # EOF on a hung-up tty
    with pytest.raises(OSError, match="Input/output error") as error:
        os.write(host.fd, b"x")
    assert error.value.errno == errno.EIO
    host.close()
    twins.throttle.replug()
    host = Host(path)
    step_for(twins, 0.0, 0.05)
    assert len(host.receive()) == 5
    host.close()


def test_a_servo_slewing_after_a_large_step_is_no_position_error(twins: ActuatorTwins) -> None:
    """Far from its setpoint but getting there at its rate: a drive's following error is
    not that. Held by hands it is, after its half second."""
    steering = host_for(twins, "steering")
    t = step_for(twins, 0.0, 0.05, steering, SteeringCommand(SteeringMode.RELEASE))
    t = step_for(twins, t, 1.2, steering, SteeringCommand(SteeringMode.POSITION, 9.0))
    last = steering.receive()[-1]
    assert isinstance(last, SteeringTelemetry)
    assert last.fault is FaultCode.NONE and twins.steering.wheel_angle_rad > 5.0
    twins.steering.operator_hands(0.0)
    step_for(twins, t, 1.0, steering, SteeringCommand(SteeringMode.POSITION, -9.0))
    last = steering.receive()[-1]
    assert isinstance(last, SteeringTelemetry) and last.fault is FaultCode.POSITION_ERROR
    steering.close()
