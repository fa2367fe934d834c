"""The vehicle file's pedal tables: the pedal sweep's plan and the simulated pedals' truth.

``[pedal_sweep]`` is what `dbw calibrate pedals` drives (``appliance.core.pedal_sweep``)
and what its fit's grid is (``calibration.pedal_map``): one place, because the sweep only
makes sense on the grid it is fitted on, and in the vehicle file rather than on the command
line because the daemon runs the sweep and a recording's replay must run the same one.
Its limits against the vehicle's (levels within the throttle and brake limits, the top
speed below the speed limit) are checked where both are known, in ``VehicleConfig``.

``[simulation.pedals]`` shapes the simulated vehicle's answer to its pedals, so the sweep
has something to find that nobody told it: a real throttle has a dead band and a
progressive cable, a brake bites more than linearly. The defaults are linear (the shape
the speed controller's built-in gains assume).
"""

from __future__ import annotations

import itertools
from typing import Protocol, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


def _increasing(name: str, values: tuple[float, ...]) -> None:
    if any(b <= a for a, b in itertools.pairwise(values)):
        raise ValueError(f"pedal_sweep.{name} must be increasing (got {list(values)})")


class PedalSweepSettings(_Model):
    """The pedal sweep: one run per level, each from standstill (Dataspeed's throttle and
    brake sweeps). A run holds its throttle level until ``top_speed_mps`` (or until the
    speed stops rising: a low level never gets there), coasts ``coast_s`` (the 0 % column
    of both maps), holds its brake level to a stop. Runs pair the levels in order; the
    shorter list repeats.

    The defaults are for the Husky (4.47 m/s limit, 45 % throttle limit): every brake
    starts from the top speed, and only the light ones fill the top band (a hard brake
    crosses it before its lag has settled). Up to about 1.2 km of straight level road in
    all, each run from a standstill: the operator can stop anywhere, turn round, and
    resume (the interrupted run starts over)."""

    top_speed_mps: float = Field(4.2, gt=0.5, le=20.0)
    throttle_levels_pct: tuple[float, ...] = Field((20.0, 30.0, 40.0), min_length=1)
    # 0: a coast-down (released down to the first band edge), the 0 % column at every speed.
    brake_levels_pct: tuple[float, ...] = Field((0.0, 5.0, 10.0, 20.0, 30.0, 40.0), min_length=1)
    # The fit's speed bands (edges); the last must be below the top speed.
    speed_band_edges_mps: tuple[float, ...] = Field((0.5, 1.5, 2.5, 3.5), min_length=2)
    coast_s: float = Field(4.0, ge=0.0, le=30.0)
    max_throttle_s: float = Field(30.0, gt=1.0, le=300.0)
    # Between runs, and when the sweep is done: the brake that holds the vehicle.
    hold_brake_pct: float = Field(40.0, gt=0.0, le=100.0)
    # Four lags of the traction and of the brake: a step's answer before it is a sample.
    traction_settle_s: float = Field(1.6, ge=0.0, le=10.0)
    brake_settle_s: float = Field(1.2, ge=0.0, le=10.0)
    # The fit's verdict: each band needs this many measured levels in each map, fewer
    # cannot show the map's shape (a short sweep on a test track may settle for 2).
    min_levels_per_band: int = Field(3, ge=2, le=10)

    @model_validator(mode="after")
    def _grid(self) -> Self:
        _increasing("throttle_levels_pct", self.throttle_levels_pct)
        _increasing("brake_levels_pct", self.brake_levels_pct)
        _increasing("speed_band_edges_mps", self.speed_band_edges_mps)
        for name, lowest in (("throttle_levels_pct", 0.0), ("brake_levels_pct", -1e-9)):
            levels: tuple[float, ...] = getattr(self, name)
            if not (levels[0] > lowest and levels[-1] <= 100.0):
                shown = "(0, 100]" if lowest == 0.0 else "[0, 100]"
                raise ValueError(f"pedal_sweep.{name} must lie in {shown} (got {list(levels)})")
        if self.speed_band_edges_mps[0] < 0.0:
            raise ValueError("pedal_sweep.speed_band_edges_mps must not be negative")
        if self.speed_band_edges_mps[-1] >= self.top_speed_mps:
            raise ValueError(
                "pedal_sweep.speed_band_edges_mps must end below top_speed_mps (got "
                f"{self.speed_band_edges_mps[-1]} >= {self.top_speed_mps}): a band the "
                "sweep never drives through stays empty"
            )
        return self


class SimPedals(_Model):
    """How the simulated vehicle answers its pedals (``appliance.sim.vehicle``): the
    fraction of full traction or braking at pedal p (0..1) is ``((p - d) / (1 - d)) ** e``
    above the dead band d, 0 below it."""

    throttle_deadband_pct: float = Field(0.0, ge=0.0, le=30.0)
    throttle_exponent: float = Field(1.0, ge=0.5, le=2.0)
    brake_deadband_pct: float = Field(0.0, ge=0.0, le=30.0)
    brake_exponent: float = Field(1.0, ge=0.5, le=2.0)


class _Limits(Protocol):
    @property
    def throttle_max_pct(self) -> float: ...
    @property
    def brake_max_pct(self) -> float: ...
    @property
    def max_speed_mps(self) -> float: ...


class _Engagement(Protocol):
    @property
    def hold_to_move(self) -> bool: ...
    @property
    def max_set_speed_mps(self) -> float: ...


def sweep_limit_problems(
    sweep: PedalSweepSettings, limits: _Limits, engagement: _Engagement
) -> list[str]:
    """What in the sweep the vehicle's limits would refuse or clamp (empty: nothing). A
    clamped level is not the level the fit files its samples under."""
    problems = []
    if sweep.throttle_levels_pct[-1] > limits.throttle_max_pct:
        problems.append(
            f"pedal_sweep.throttle_levels_pct goes to {sweep.throttle_levels_pct[-1]}, "
            f"past limits.throttle_max_pct ({limits.throttle_max_pct})"
        )
    if max(sweep.brake_levels_pct[-1], sweep.hold_brake_pct) > limits.brake_max_pct:
        problems.append(
            "pedal_sweep's brake levels (and hold_brake_pct) must not pass "
            f"limits.brake_max_pct ({limits.brake_max_pct})"
        )
    if sweep.top_speed_mps > limits.max_speed_mps:
        problems.append(
            f"pedal_sweep.top_speed_mps ({sweep.top_speed_mps}) must not exceed "
            f"limits.max_speed_mps ({limits.max_speed_mps})"
        )
    if engagement.hold_to_move and sweep.top_speed_mps > engagement.max_set_speed_mps:
        # The released button's stop distance is worked out from the top set speed.
        problems.append(
            f"pedal_sweep.top_speed_mps ({sweep.top_speed_mps}) must not exceed "
            f"engagement.max_set_speed_mps ({engagement.max_set_speed_mps}) under "
            "hold-to-move"
        )
    return problems
