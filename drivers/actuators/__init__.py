"""Serial actuator boards: steering servo (with the steering pot), throttle, brake, panel.

``framing``/``messages``/``protocol`` are the sans-I/O core (docs/protocols/actuator-boards.md),
``client`` the asyncio transport with staleness and reconnect, ``twin`` a simulated board on a
pseudo-terminal (its protocol side) and ``steering_model`` the servo and pot physics. The
runtime wires the four clients of a vehicle profile (``appliance.board_clients``); the four
boards wired to the simulated world live with the simulator (``appliance.sim.twins``).
"""

from drivers.actuators.framing import ActuatorProtocolError
from drivers.actuators.messages import (
    BoardKind,
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

__all__ = [
    "NEED_DATA",
    "ActuatorCodec",
    "ActuatorProtocolError",
    "BoardKind",
    "BoardStatus",
    "BrakeCommand",
    "BrakeTelemetry",
    "Buttons",
    "Command",
    "FaultCode",
    "Lamps",
    "PanelCommand",
    "PanelTelemetry",
    "Role",
    "SteeringCommand",
    "SteeringMode",
    "SteeringTelemetry",
    "Telemetry",
    "ThrottleCommand",
    "ThrottleTelemetry",
]
