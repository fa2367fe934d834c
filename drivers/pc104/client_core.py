"""The client's pure parts: its parameters, topics and health, and the command rule.

Kept apart from the asyncio loop in :mod:`drivers.pc104.client` so that the rule deciding
what goes out to the PC104 is a plain function with a table test over every case.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.pc104.errorframes import BusCondition
from drivers.pc104.messages import (
    ControlSource,
    Inclinometer,
    MotionCommand,
    MotionPattern,
    MotorPulses,
    Pc104Heartbeat,
    Pc104Status,
    WheelAngles,
)
from drivers.topics import Topic


@dataclass(frozen=True)
class Pc104Topics:
    status: Topic[Pc104Status]
    wheel_angles: Topic[WheelAngles]
    motor_pulses: Topic[MotorPulses]
    inclinometer: Topic[Inclinometer]
    heartbeat: Topic[Pc104Heartbeat]

    @classmethod
    def create(cls, prefix: str = "pc104") -> Pc104Topics:
        return cls(
            Topic(f"{prefix}.status"),
            Topic(f"{prefix}.wheel_angles"),
            Topic(f"{prefix}.motor_pulses"),
            Topic(f"{prefix}.inclinometer"),
            Topic(f"{prefix}.heartbeat"),
        )


@dataclass(frozen=True)
class ClientParams:
    command_period_s: float = 0.02
    status_max_age_s: float = 0.1
    command_timeout_s: float = 0.1
    reopen_initial_backoff_s: float = 0.05
    reopen_backoff_factor: float = 2.0
    reopen_backoff_cap_s: float = 1.0
    bus_state_poll_s: float = 1.0


@dataclass(frozen=True)
class LinkHealth:
    connected: bool
    stale: bool  # no valid PC104_Status for more than status_max_age_s
    status_age_s: float
    frames_in_per_s: float
    frames_out_per_s: float
    frames_received: int  # every frame read off the bus, good or bad (a monotonic total)
    crc_errors: int
    malformed_frames: int  # wrong length or a value outside the DBC
    counter_errors: int  # stuck + skipped + jumped counters, all PC104 messages
    late_frames: int
    send_drops: int
    resyncs: int
    reconnects: int
    bus_condition: BusCondition
    control_source: ControlSource | None
    peer_ready: bool
    holding_stop: bool  # motion was replaced by STOP; the control loop must send STOP
    stale_since_s: float | None  # when the loop noticed the status going stale
    last_error: str


class RateMeter:
    """Frames per second over the last full window (pure; time is an argument)."""

    def __init__(self, window_s: float = 1.0) -> None:
        self.window_s = window_s
        self.rate_per_s = 0.0
        self._start_s: float | None = None
        self._start_total = 0

    def update(self, now_s: float, total: int) -> None:
        if self._start_s is None:
            self._start_s, self._start_total = now_s, total
        elif now_s - self._start_s >= self.window_s:
            self.rate_per_s = (total - self._start_total) / (now_s - self._start_s)
            self._start_s, self._start_total = now_s, total


def command_to_send(
    latest: MotionCommand | None,
    latest_s: float,
    now_s: float,
    timeout_s: float,
    status: Pc104Status | None,
    status_fresh: bool,
    holding: bool,
) -> tuple[MotionCommand, str, bool]:
    """The command that goes out now, why it is a substituted STOP ("" if it is not), and
    whether the client holds STOP from now on.

    Once a motion command has been replaced by STOP, the client keeps sending STOP until
    the control loop itself sends STOP: like the PC104, it never lets motion resume just
    because the condition that stopped it went away.
    """
    if latest is None:
        return MotionCommand.stop(), "no command yet", holding
    if latest.pattern is MotionPattern.STOP:
        return latest, "", False
    if holding:
        return MotionCommand.stop(), "holding STOP until the control loop sends STOP", True
    if now_s - latest_s > timeout_s:
        why = "command older than lower_layer_command_timeout_s"
    elif not status_fresh or status is None:
        why = "PC104 status stale"
    elif status.control_source is not ControlSource.AUTOMATIC:
        why = f"PC104 under {status.control_source} control"
    else:
        return latest, "", False
    return MotionCommand.stop(), why, True
