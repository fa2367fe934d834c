"""The autopilot seam: where steering and speed wishes come from when the operator engages.

Until guidance exists (routes, pure pursuit, docking), a source is a small class that
looks at the cycle's observation and returns a wish; the core passes every wish through
the mode machine and the safety layer, so a source can never command anything the
operator did not engage. Plugging in a new source is one line in ``AUTOPILOT_SOURCES``
(and ``engagement.autopilot_source = "<name>"`` in the vehicle file).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from appliance.config import parts
from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig, VehicleKind
from appliance.core.pallet_autopilot import PalletAutopilot
from appliance.core.route_autopilot import RouteAutopilot
from appliance.core.wish import AutopilotSource, AutopilotWish, Observation
from appliance.guidance.dock_source import DockSource
from drivers.pc104.messages import MotionPattern, PoseState


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


class DockAutopilot:
    """Qian et al.'s docking (``appliance.guidance.dock_source``) on this seam."""

    name = "dock"

    def __init__(self, source: DockSource) -> None:
        self.source = source

    def reset(self) -> None:
        self.source.reset()

    def launcher(self) -> dict[str, object]:
        """The launcher's geometry as the localizer knows it, for the operator page's
        Fig. 8 view (asked at status time, not every cycle)."""
        launcher = self.source.localizer.params.launcher
        return {
            "front_board_width_m": launcher.front_board_width_m,
            "side_board_length_m": launcher.side_board_length_m,
            "side_board_sweep_deg": launcher.side_board_sweep_deg,
            "cylinders": [
                {"name": c.name, "x_m": c.x_m, "y_m": c.y_m, "radius_m": c.radius_m}
                for c in launcher.cylinders
            ],
        }

    def update(self, observation: Observation) -> AutopilotWish:
        wish = self.source.wish(observation.scans, observation.engaged, observation.now_s)
        return AutopilotWish(
            ready=wish.ready,
            reason=wish.reason,
            steer_tyre_rad=wish.front_steer_rad,
            max_speed_mps=abs(wish.speed_mps),
            pattern=wish.pattern,
            rear_steer_rad=wish.rear_steer_rad,
            reverse=wish.speed_mps < 0.0,
            status=wish.status,
            pose=wish.pose,
            pose_state=PoseState(str(wish.pose_status)),
            expected_pose=wish.expected_pose,
        )


def _dock_source(config: VehicleConfig, calibration: Calibration | None) -> AutopilotSource:
    if config.kind is not VehicleKind.FLATBED:
        raise ValueError(f"autopilot source 'dock' needs a flat-bed vehicle, not {config.kind}")
    source = DockSource(parts.scanner_setups(config, calibration), parts.dock_source_params(config))
    return DockAutopilot(source)


def _route_source(config: VehicleConfig, calibration: Calibration | None) -> AutopilotSource:
    schedule = None if calibration is None else calibration.guidance_schedule
    return RouteAutopilot(config, schedule=schedule)


def _pallet_source(config: VehicleConfig, calibration: Calibration | None) -> AutopilotSource:
    if config.kind is not VehicleKind.FORKLIFT:
        raise ValueError(f"autopilot source 'pallet' needs a forklift, not {config.kind}")
    return PalletAutopilot(config, calibration)


SourceFactory = Callable[[VehicleConfig, "Calibration | None"], AutopilotSource]

AUTOPILOT_SOURCES: dict[str, SourceFactory] = {
    "hold_straight": lambda _config, _calibration: HoldStraight(),
    "weave": lambda _config, _calibration: Weave(),
    "dock": _dock_source,
    "route": _route_source,
    "pallet": _pallet_source,
}


def make_source(config: VehicleConfig, calibration: Calibration | None = None) -> AutopilotSource:
    name = config.engagement.autopilot_source
    factory = AUTOPILOT_SOURCES.get(name)
    if factory is None:
        known = ", ".join(sorted(AUTOPILOT_SOURCES))
        raise ValueError(f"engagement.autopilot_source {name!r} is not one of: {known}")
    return factory(config, calibration)


def default_pattern(kind: VehicleKind) -> MotionPattern:
    """The pattern the PC104 is asked for when a source does not name one."""
    match kind:
        case VehicleKind.FOUR_WHEEL_COUNTER_STEER:
            return MotionPattern.COUNTER_STEER
        case VehicleKind.FLATBED | VehicleKind.FRONT_STEER:
            return MotionPattern.FRONT_STEER
        case VehicleKind.FORKLIFT:
            return MotionPattern.REAR_STEER
    raise ValueError(f"no default pattern for {kind}")


__all__ = [
    "AUTOPILOT_SOURCES",
    "AutopilotSource",
    "AutopilotWish",
    "DockAutopilot",
    "HoldStraight",
    "Observation",
    "PalletAutopilot",
    "RouteAutopilot",
    "Weave",
    "WeaveParams",
    "default_pattern",
    "make_source",
]
