"""Client construction and command validation: what fails before anything is sent."""

from __future__ import annotations

import pytest

from appliance.board_clients import make_board_clients
from appliance.config import load_config
from drivers.actuators.client import ActuatorClient
from drivers.actuators.framing import ActuatorProtocolError
from drivers.actuators.messages import (
    BoardKind,
    BrakeCommand,
    SteeringCommand,
    SteeringMode,
    SteeringTelemetry,
)


def test_clients_take_their_age_limits_from_the_profile() -> None:
    config = load_config("sim")
    clients = make_board_clients(config, lambda port: "/tmp/" + port.removeprefix("sim://"))
    assert clients.steering.port == "/tmp/steering"
    assert clients.steering.max_age_s == config.staleness.steering_pot_max_age_s
    assert clients.brake.max_age_s == config.staleness.actuator_board_max_age_s
    assert clients.panel.max_age_s == config.staleness.panel_max_age_s
    assert [c.board for c in clients.all()] == list(BoardKind)


def test_sim_ports_need_the_twins() -> None:
    with pytest.raises(ValueError, match="simulated boards"):
        make_board_clients(load_config("sim"))
    with pytest.raises(ValueError, match="resolved"):
        ActuatorClient(SteeringTelemetry, "sim://steering")


def test_commands_are_checked_before_they_are_stored() -> None:
    client = ActuatorClient(SteeringTelemetry, "/dev/null")
    with pytest.raises(ActuatorProtocolError):
        client.set_command(BrakeCommand(True, 50.0))
    with pytest.raises(ActuatorProtocolError):
        client.set_command(SteeringCommand(SteeringMode.POSITION, 99.0))
    assert client.command is None
    client.set_command(SteeringCommand(SteeringMode.RELEASE))  # not connected: stored only
    assert client.command == SteeringCommand(SteeringMode.RELEASE)
    assert client.commands_sent == 0
    client.clear_command()
    assert client.command is None
    health = client.health(now_s=0.0)
    assert not health.connected and health.stale and not health.healthy
