"""What the speed controller assumes of the vehicle's pedals: acceleration to pedal and back.

The throttle/brake controller (:mod:`appliance.guidance.pedal_speed`) plans in m/s² and
needs three things of the plant: how much the vehicle decelerates with both pedals
released (drag, the feed-forward that holds a speed), which pedal position gives a wanted
acceleration at a speed, and how much the engine can give at all. :class:`LinearPlant` is
the controller's built-in model (a gain per pedal and a drag proportional to speed: the
simulated vehicle's as shipped). :class:`MapPlant` is the pedal sweep's measurement
(`dbw calibrate pedals`, the calibration file's ``[pedals]``): acceleration per pedal level
at each speed band's centre, interpolated linearly in speed between centres (held beyond
the first and last) and in the pedal between levels. The maps are monotonic (the fit made
them so), so each has one inverse. Beyond what was measured (an acceleration past the
highest level measured at that speed, a band without a level) the linear model's gain
continues from the last measured point: the map is trusted where it was measured, and
nowhere is a pedal position left undefined.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class PedalPlant(Protocol):
    """``effort_mps2`` is the acceleration wanted *above coasting's* at that speed (what
    the controller's pedal split is decided on): 0 is both pedals released."""

    def coast_accel_mps2(self, speed_mps: float) -> float:
        """Acceleration with both pedals released (negative: drag)."""
        ...

    def throttle_pct(self, effort_mps2: float, speed_mps: float) -> float:
        """The throttle for an effort (0 for none or less; not clamped above)."""
        ...

    def brake_pct(self, effort_mps2: float, speed_mps: float) -> float:
        """The brake for a (negative) effort (0 for none or more; not clamped above)."""
        ...

    def accel_at_throttle_mps2(self, throttle_pct: float, speed_mps: float) -> float:
        """The net acceleration a throttle position gives (the engine's capacity)."""
        ...


@dataclass(frozen=True)
class LinearPlant:
    accel_per_throttle_pct_mps2: float
    decel_per_brake_pct_mps2: float
    drag_per_s: float

    def coast_accel_mps2(self, speed_mps: float) -> float:
        return -self.drag_per_s * speed_mps

    def throttle_pct(self, effort_mps2: float, speed_mps: float) -> float:
        return max(0.0, effort_mps2) / self.accel_per_throttle_pct_mps2

    def brake_pct(self, effort_mps2: float, speed_mps: float) -> float:
        return max(0.0, -effort_mps2) / self.decel_per_brake_pct_mps2

    def accel_at_throttle_mps2(self, throttle_pct: float, speed_mps: float) -> float:
        return throttle_pct * self.accel_per_throttle_pct_mps2 - self.drag_per_s * speed_mps


@dataclass(frozen=True)
class PedalTable:
    """One pedal's measured map: ``accel_mps2[level, band]``, NaN where not measured."""

    pedal_pct: tuple[float, ...]
    speed_mps: tuple[float, ...]
    accel_mps2: tuple[tuple[float, ...], ...]  # per level, per band

    @cached_property
    def _arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The tables as arrays, made once: ``curve`` runs a few times per control cycle."""
        return (
            np.asarray(self.pedal_pct, dtype=np.float64),
            np.asarray(self.speed_mps, dtype=np.float64),
            np.asarray(self.accel_mps2, dtype=np.float64),
        )

    def curve(self, speed_mps: float) -> tuple[FloatArray, FloatArray]:
        """(levels, accelerations) at ``speed_mps``: the levels measured in both bands
        around it (or in the nearest band outside them)."""
        levels, speeds, values = self._arrays
        if speeds.size == 1 or speed_mps <= speeds[0]:
            column = values[:, 0]
        elif speed_mps >= speeds[-1]:
            column = values[:, -1]
        else:
            high = int(np.searchsorted(speeds, speed_mps, side="right"))
            weight = (speed_mps - speeds[high - 1]) / (speeds[high] - speeds[high - 1])
            column = (1.0 - weight) * values[:, high - 1] + weight * values[:, high]
        known = np.isfinite(column)
        return levels[known], column[known]


@dataclass(frozen=True)
class MapPlant:
    """The pedal sweep's maps, with ``linear`` beyond them (see the module)."""

    throttle: PedalTable
    brake: PedalTable
    linear: LinearPlant

    def coast_accel_mps2(self, speed_mps: float) -> float:
        for table in (self.throttle, self.brake):
            levels, accel = table.curve(speed_mps)
            if levels.size and levels[0] == 0.0:
                return float(accel[0])
        return self.linear.coast_accel_mps2(speed_mps)

    def throttle_pct(self, effort_mps2: float, speed_mps: float) -> float:
        gain = self.linear.accel_per_throttle_pct_mps2
        coast = self.coast_accel_mps2(speed_mps)
        return _invert(self.throttle, effort_mps2 + coast, speed_mps, gain, coast)

    def brake_pct(self, effort_mps2: float, speed_mps: float) -> float:
        gain = self.linear.decel_per_brake_pct_mps2
        coast = self.coast_accel_mps2(speed_mps)
        return _invert(self.brake, -(effort_mps2 + coast), speed_mps, gain, -coast, negate=True)

    def accel_at_throttle_mps2(self, throttle_pct: float, speed_mps: float) -> float:
        levels, accel = _with_coast(self.throttle, speed_mps, self.coast_accel_mps2(speed_mps))
        if throttle_pct <= levels[-1]:
            return float(np.interp(throttle_pct, levels, accel))
        gain = self.linear.accel_per_throttle_pct_mps2
        return float(accel[-1] + gain * (throttle_pct - levels[-1]))


def _with_coast(
    table: PedalTable, speed_mps: float, coast_mps2: float, negate: bool = False
) -> tuple[FloatArray, FloatArray]:
    """The table's curve at a speed, rising, starting from coasting at 0 %."""
    levels, accel = table.curve(speed_mps)
    if negate:
        accel = -accel
    if not levels.size or levels[0] != 0.0:
        levels = np.concatenate(([0.0], levels))
        accel = np.concatenate(([coast_mps2], accel))
    # The fit made each band monotonic; interpolating two bands keeps it so. A coast
    # taken from the other map or the linear model may not fit: never let it fold.
    return levels, np.maximum.accumulate(accel)


def _invert(
    table: PedalTable,
    wanted_mps2: float,
    speed_mps: float,
    gain_per_pct: float,
    coast_mps2: float,
    negate: bool = False,
) -> float:
    if not math.isfinite(wanted_mps2):
        return math.nan
    levels, accel = _with_coast(table, speed_mps, coast_mps2, negate)
    if wanted_mps2 <= accel[0]:
        return 0.0
    if wanted_mps2 > accel[-1]:
        return float(levels[-1] + (wanted_mps2 - accel[-1]) / gain_per_pct)
    # The first level that reaches the wish, and the one before it (plateaus: the lowest).
    index = int(np.searchsorted(accel, wanted_mps2, side="left"))
    a0, a1 = accel[index - 1], accel[index]
    p0, p1 = levels[index - 1], levels[index]
    return float(p1 if a1 == a0 else p0 + (p1 - p0) * (wanted_mps2 - a0) / (a1 - a0))


def table_from_bands(
    pedal_pct: Sequence[float],
    speed_mps: Sequence[float],
    first_level_by_band: Sequence[int],
    accel_mps2_by_band: Sequence[Sequence[float]],
) -> PedalTable:
    """The calibration file's form (per band, its contiguous levels) as a full table."""
    grid = [[math.nan] * len(speed_mps) for _ in pedal_pct]
    for band, (first, row) in enumerate(zip(first_level_by_band, accel_mps2_by_band, strict=True)):
        for offset, value in enumerate(row):
            grid[first + offset][band] = float(value)
    return PedalTable(
        tuple(float(p) for p in pedal_pct),
        tuple(float(v) for v in speed_mps),
        tuple(tuple(row) for row in grid),
    )
