"""The four board clients of a vehicle profile, as the daemon wires them.

Staleness limits come from the profile: the steering board carries the steering pot, a
control input, so it gets ``steering_pot_max_age_s``; throttle and brake get
``actuator_board_max_age_s``; the panel ``panel_max_age_s``. ``sim://`` ports are resolved
through the simulated boards (``ActuatorTwins.port_path``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from appliance.config.models import VehicleConfig
from drivers.actuators.client import DEFAULT_COMMAND_PERIOD_S, ActuatorClient
from drivers.actuators.messages import (
    BrakeTelemetry,
    PanelTelemetry,
    SteeringTelemetry,
    ThrottleTelemetry,
)
from drivers.ptylink import SIM_PORT_PREFIX


@dataclass(frozen=True)
class BoardClients:
    steering: ActuatorClient[SteeringTelemetry]
    throttle: ActuatorClient[ThrottleTelemetry]
    brake: ActuatorClient[BrakeTelemetry]
    panel: ActuatorClient[PanelTelemetry]

    def all(self) -> tuple[ActuatorClient[Any], ...]:
        return (self.steering, self.throttle, self.brake, self.panel)


def make_board_clients(
    config: VehicleConfig,
    resolve_sim_port: Callable[[str], str] | None = None,
    *,
    beat_while_reconnecting: bool = False,
    backoff_cap_s: float = 1.0,
) -> BoardClients:
    """The four clients of a vehicle profile; ``sim://`` ports go through ``resolve_sim_port``
    (``ActuatorTwins.port_path``), real ones are used as they are."""
    if config.safety.lower_layer_command_timeout_s < 3 * DEFAULT_COMMAND_PERIOD_S:
        raise ValueError(
            "safety.lower_layer_command_timeout_s must allow three command periods "
            f"({3 * DEFAULT_COMMAND_PERIOD_S:.3f} s)"
        )
    devices, ages = config.devices, config.staleness

    def port(endpoint_port: str) -> str:
        if endpoint_port.startswith(SIM_PORT_PREFIX):
            if resolve_sim_port is None:
                raise ValueError(f"{endpoint_port!r} needs the simulated boards (ActuatorTwins)")
            return resolve_sim_port(endpoint_port)
        return endpoint_port

    return BoardClients(
        steering=ActuatorClient(
            SteeringTelemetry,
            port(devices.steering_serial.port),
            baudrate_bps=devices.steering_serial.baudrate_bps,
            max_age_s=ages.steering_pot_max_age_s,
            beat_while_reconnecting=beat_while_reconnecting,
            backoff_cap_s=backoff_cap_s,
        ),
        throttle=ActuatorClient(
            ThrottleTelemetry,
            port(devices.throttle_serial.port),
            baudrate_bps=devices.throttle_serial.baudrate_bps,
            max_age_s=ages.actuator_board_max_age_s,
            beat_while_reconnecting=beat_while_reconnecting,
            backoff_cap_s=backoff_cap_s,
        ),
        brake=ActuatorClient(
            BrakeTelemetry,
            port(devices.brake_serial.port),
            baudrate_bps=devices.brake_serial.baudrate_bps,
            max_age_s=ages.actuator_board_max_age_s,
            beat_while_reconnecting=beat_while_reconnecting,
            backoff_cap_s=backoff_cap_s,
        ),
        panel=ActuatorClient(
            PanelTelemetry,
            port(devices.panel_serial.port),
            baudrate_bps=devices.panel_serial.baudrate_bps,
            max_age_s=ages.panel_max_age_s,
            beat_while_reconnecting=beat_while_reconnecting,
            backoff_cap_s=backoff_cap_s,
        ),
    )
