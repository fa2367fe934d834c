"""The autopilot seam: where steering and speed wishes come from when the operator engages.

Until guidance exists (routes, pure pursuit, docking), a source is a small class that
looks at the cycle's observation and returns a wish; the core passes every wish through
the mode machine and the safety layer, so a source can never command anything the
operator did not engage. Plugging in a new source is one line in ``AUTOPILOT_SOURCES``
(and ``engagement.autopilot_source = "<name>"`` in the vehicle file).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

from appliance.config.models import VehicleConfig, VehicleKind
from drivers.lms111.mounted import MountedScan
from drivers.pc104.messages import MotionPattern


@dataclass(frozen=True)
class Observation:
    """What a source may look at this cycle (all optional: inputs can be missing)."""

    now_s: float
    speed_mps: float | None
    steer_tyre_rad: float | None
    scans: Mapping[str, MountedScan | None] = field(default_factory=dict)


@dataclass(frozen=True)
class AutopilotWish:
    """A source's wish for this cycle.

    ``ready=False`` refuses engagement with ``reason`` (and disengages if it happens while
    engaged: a source that lost its route cannot steer). ``max_speed_mps`` caps the
    operator's set speed (a route's speed limit); None leaves it alone.
    """

    ready: bool
    reason: str = ""
    steer_tyre_rad: float = 0.0
    max_speed_mps: float | None = None
    pattern: MotionPattern | None = None  # None: the vehicle's default pattern


class AutopilotSource(Protocol):
    name: str

    def reset(self) -> None: ...

    def update(self, observation: Observation) -> AutopilotWish: ...


class HoldStraight:
    """Keeps the wheels straight ahead: the bench source, and the demo's default."""

    name = "hold_straight"

    def reset(self) -> None:
        pass

    def update(self, observation: Observation) -> AutopilotWish:
        return AutopilotWish(ready=True, steer_tyre_rad=0.0)


@dataclass(frozen=True)
class WeaveParams:
    amplitude_rad: float = math.radians(5.0)
    period_s: float = 8.0


class Weave:
    """A slow sine on the steering: makes tracking, limits and override visible on a bench."""

    name = "weave"

    def __init__(self, params: WeaveParams = WeaveParams()) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._start_s: float | None = None

    def update(self, observation: Observation) -> AutopilotWish:
        if self._start_s is None:
            self._start_s = observation.now_s
        phase = 2.0 * math.pi * (observation.now_s - self._start_s) / self.params.period_s
        return AutopilotWish(ready=True, steer_tyre_rad=self.params.amplitude_rad * math.sin(phase))


AUTOPILOT_SOURCES: dict[str, Callable[[VehicleConfig], AutopilotSource]] = {
    "hold_straight": lambda _config: HoldStraight(),
    "weave": lambda _config: Weave(),
}


def make_source(config: VehicleConfig) -> AutopilotSource:
    name = config.engagement.autopilot_source
    factory = AUTOPILOT_SOURCES.get(name)
    if factory is None:
        known = ", ".join(sorted(AUTOPILOT_SOURCES))
        raise ValueError(f"engagement.autopilot_source {name!r} is not one of: {known}")
    return factory(config)


def default_pattern(kind: VehicleKind) -> MotionPattern:
    """The pattern the PC104 is asked for when a source does not name one."""
    match kind:
        case VehicleKind.FOUR_WHEEL_COUNTER_STEER:
            return MotionPattern.COUNTER_STEER
        case VehicleKind.FLATBED | VehicleKind.FRONT_STEER:
            return MotionPattern.FRONT_STEER
    raise ValueError(f"no default pattern for {kind}")
