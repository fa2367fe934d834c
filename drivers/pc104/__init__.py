"""The CAN link to the vehicle's PC104 lower-level controller (Qian et al., section 2.2.2).

``pc104.dbc`` is the contract; :mod:`.protocol` the sans-I/O codec; :mod:`.monitor` the
receive checks; :mod:`.client` the daemon's asyncio end and :mod:`.sender` the frames it
sends. The simulated controller that speaks the same contract lives with the simulator
(``appliance.sim.twins.pc104``).
docs/protocols/pc104-can.md describes the link for whoever wires the vehicle.
"""

from drivers.pc104.client import Pc104Client
from drivers.pc104.client_core import ClientParams, LinkHealth, Pc104Topics
from drivers.pc104.errorframes import BusCondition
from drivers.pc104.messages import (
    PROTOCOL_VERSION,
    ControlSource,
    HighLevelState,
    HlHeartbeat,
    Inclinometer,
    MotionCommand,
    MotionPattern,
    MotorPulses,
    Pc104Faults,
    Pc104Heartbeat,
    Pc104State,
    Pc104Status,
    WheelAngles,
    pulse_delta,
)
from drivers.pc104.monitor import MonitorCounts, MonitorParams, ReceiveMonitor, RxVerdict
from drivers.pc104.protocol import (
    CommandRefused,
    DecodedFrame,
    ErrorReason,
    Pc104ProtocolError,
    crc8_j1850,
    decode,
    encode,
)

__all__ = [
    "PROTOCOL_VERSION",
    "BusCondition",
    "ClientParams",
    "CommandRefused",
    "ControlSource",
    "DecodedFrame",
    "ErrorReason",
    "HighLevelState",
    "HlHeartbeat",
    "Inclinometer",
    "LinkHealth",
    "MonitorCounts",
    "MonitorParams",
    "MotionCommand",
    "MotionPattern",
    "MotorPulses",
    "Pc104Client",
    "Pc104Faults",
    "Pc104Heartbeat",
    "Pc104ProtocolError",
    "Pc104State",
    "Pc104Status",
    "Pc104Topics",
    "ReceiveMonitor",
    "RxVerdict",
    "WheelAngles",
    "crc8_j1850",
    "decode",
    "encode",
    "pulse_delta",
]
