"""The PC104 link's messages as typed values in SI units: what the rest of the daemon sees.

These are plain frozen dataclasses with no knowledge of bits, counters or checksums; the
codec in :mod:`drivers.pc104.protocol` maps them to and from the frames that
``pc104.dbc`` defines. Keeping framing out of them means a recorded or simulated status
looks exactly like one that came off the bus.

Angles are physical wheel angles, positive = turned left (counter-clockwise seen from
above), for the command and the measurements alike. Note that the simulated vehicle's
``VehicleCommand.rear_steer_rad`` counts the other way (positive = counter-steer
direction); the twin converts at its edge, and so must any code that builds a
``MotionCommand`` from the guidance's counter-steer convention.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

# The major version of pc104.dbc this code implements; sent in both heartbeats.
PROTOCOL_VERSION = 1


class MotionPattern(StrEnum):
    """The motion patterns of the PC104 lower-level controller (Qian et al. section 2.1)."""

    STOP = "stop"
    STRAIGHT = "straight"
    OBLIQUE = "oblique"  # crab: all wheels parallel at the crab angle
    FRONT_STEER = "front_steer"
    REAR_STEER = "rear_steer"
    COUNTER_STEER = "counter_steer"  # proportional: phi_r = k * phi_f
    TURN_AROUND = "turn_around"  # rotate in place about the geometric centre


class ControlSource(StrEnum):
    """Who drives the vehicle, as the PC104 reports it (its own selector decides, not us)."""

    CAB = "cab"
    REMOTE = "remote"
    AUTOMATIC = "automatic"


class HighLevelState(StrEnum):
    INIT = "init"
    STANDBY = "standby"  # alive, not commanding motion
    ENGAGED = "engaged"  # commanding motion
    FAULT = "fault"


class Pc104State(StrEnum):
    BOOT = "boot"
    RUNNING = "running"
    FAULT = "fault"


@dataclass(frozen=True)
class MotionCommand:
    """HL -> PC104 at the control rate. Which setpoints a pattern uses is in pc104.dbc."""

    pattern: MotionPattern
    speed_mps: float = 0.0  # signed: negative = reverse
    front_steer_rad: float = 0.0  # also the crab angle in OBLIQUE; positive = left
    rear_steer_rad: float = 0.0  # REAR_STEER only; physical angle, positive = left
    level_platform: bool = False

    @classmethod
    def stop(cls) -> MotionCommand:
        return cls(MotionPattern.STOP)


class PoseState(StrEnum):
    """How far the high level trusts the pose it sends (its localization status)."""

    LOST = "lost"
    DEGRADED = "degraded"
    OK = "ok"


class SteeringLoop(StrEnum):
    """Who turns the pose error into wheel angles (HL_ExpectedPose.SteeringLoop)."""

    HL = "hl"  # the PC104 follows HL_MotionCommand's steer set-points
    PC104 = "pc104"  # the PC104's PID per pattern on HL_Pose and HL_ExpectedPose


@dataclass(frozen=True)
class HlPose:
    """HL -> PC104: the geometric centre's pose in the site frame, with its trust."""

    x_m: float
    y_m: float
    yaw_rad: float  # in [-pi, pi]
    state: PoseState = PoseState.OK


@dataclass(frozen=True)
class HlExpectedPose:
    """HL -> PC104: where the plan takes the geometric centre, and who steers there."""

    x_m: float
    y_m: float
    yaw_rad: float  # in [-pi, pi]
    loop: SteeringLoop = SteeringLoop.HL


@dataclass(frozen=True)
class HlHeartbeat:
    state: HighLevelState
    protocol_version: int = PROTOCOL_VERSION


@dataclass(frozen=True)
class Pc104Faults:
    command_timeout: bool = False
    command_invalid: bool = False
    hydraulic: bool = False
    steering: bool = False
    encoder: bool = False
    inclinometer: bool = False
    motor_pulses: bool = False
    pose: bool = False  # closing the loop on pose, and the pose is missing or not OK

    @property
    def any(self) -> bool:
        return any(getattr(self, name) for name in self.__dataclass_fields__)


@dataclass(frozen=True)
class Pc104Status:
    active_pattern: MotionPattern
    ready: bool
    control_source: ControlSource
    platform_leveling: bool = False
    emergency_stop: bool = False
    stop_required: bool = False
    faults: Pc104Faults = Pc104Faults()
    measured_speed_mps: float = 0.0
    bad_command_frames: int = 0  # wraps at 256


ROW_COUNT = 4


@dataclass(frozen=True)
class WheelAngles:
    """Encoder angle per steered row, front (index 0) to rear (index 3)."""

    row_angles_rad: tuple[float, float, float, float]
    row_valid: tuple[bool, bool, bool, bool] = (True, True, True, True)

    @property
    def front_rad(self) -> float:
        return self.row_angles_rad[0]

    @property
    def rear_rad(self) -> float:
        return self.row_angles_rad[-1]


PULSE_COUNTER_MODULO = 4096


def pulse_delta(previous_counts: int, current_counts: int) -> int:
    """Pulses between two readings of a wrapping 12-bit motor counter (counts up only).

    Unambiguous while fewer than 4096 pulses pass between the two frames, i.e. for any
    speed a heavy vehicle reaches unless a whole second of frames is lost.
    """
    return (current_counts - previous_counts) % PULSE_COUNTER_MODULO


@dataclass(frozen=True)
class MotorPulses:
    front_left_counts: int
    front_right_counts: int
    rear_left_counts: int
    rear_right_counts: int


@dataclass(frozen=True)
class Inclinometer:
    pitch_rad: float  # positive = front up
    roll_rad: float  # positive = left side up
    valid: bool = True


@dataclass(frozen=True)
class Pc104Heartbeat:
    state: Pc104State
    uptime_s: int  # wraps at 65536; a decrease means the PC104 restarted
    protocol_version: int = PROTOCOL_VERSION


HlMessage = MotionCommand | HlHeartbeat | HlPose | HlExpectedPose
Pc104Message = Pc104Status | WheelAngles | MotorPulses | Inclinometer | Pc104Heartbeat
Message = HlMessage | Pc104Message

__all__ = [
    "PROTOCOL_VERSION",
    "PULSE_COUNTER_MODULO",
    "ROW_COUNT",
    "ControlSource",
    "HighLevelState",
    "HlExpectedPose",
    "HlHeartbeat",
    "HlMessage",
    "HlPose",
    "Inclinometer",
    "Message",
    "MotionCommand",
    "MotionPattern",
    "MotorPulses",
    "Pc104Faults",
    "Pc104Heartbeat",
    "Pc104Message",
    "Pc104State",
    "Pc104Status",
    "PoseState",
    "SteeringLoop",
    "WheelAngles",
    "pulse_delta",
]
