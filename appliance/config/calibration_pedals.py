"""The calibration file's ``[pedals.throttle]`` and ``[pedals.brake]``: the pedal maps.

What `dbw calibrate pedals` measured (``calibration.pedal_map``): the acceleration each
pedal level gives at each speed band's centre, on the flat. A map holds only what was
measured, or interpolated between measured levels of one band; nothing is extrapolated.
TOML has no NaN to mark a cell nobody measured, so each band keeps the contiguous run of
levels it has: ``accel_mps2_by_band[b]`` holds the values of levels ``first_level_by_band[b]``
onward (an empty list: the band was not measured). Checked on reading like everything in
the file: shapes, finite values, and the monotonic order the fit guarantees (more throttle
never less acceleration, more brake never less deceleration), since a map that folds back
cannot be inverted into a pedal position.

Optional, added after version 1 like ``[scanners]``: a file without it still loads.
"""

from __future__ import annotations

import itertools
import math
from typing import Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

MAX_ACCEL_MPS2 = 15.0  # beyond any road vehicle's pedal: a unit or sign mistake


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class PedalMapTable(_Model):
    """One pedal's map (see the module)."""

    pedal_pct: tuple[float, ...] = Field(min_length=1)  # the levels, increasing
    speed_mps: tuple[float, ...] = Field(min_length=1)  # the bands' centres, increasing
    first_level_by_band: tuple[int, ...]
    accel_mps2_by_band: tuple[tuple[float, ...], ...]

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        for name in ("pedal_pct", "speed_mps"):
            values: tuple[float, ...] = getattr(self, name)
            if not all(math.isfinite(v) for v in values) or any(
                b <= a for a, b in itertools.pairwise(values)
            ):
                raise ValueError(f"{name} must be finite and increasing (got {list(values)})")
        bands = len(self.speed_mps)
        if len(self.first_level_by_band) != bands or len(self.accel_mps2_by_band) != bands:
            raise ValueError(
                f"first_level_by_band and accel_mps2_by_band need one entry per band ({bands})"
            )
        for first, row in zip(self.first_level_by_band, self.accel_mps2_by_band, strict=True):
            if first < 0 or first + len(row) > len(self.pedal_pct):
                raise ValueError(
                    f"a band's levels {first}..{first + len(row) - 1} are not all among the "
                    f"{len(self.pedal_pct)} pedal levels"
                )
            if not all(math.isfinite(a) and abs(a) <= MAX_ACCEL_MPS2 for a in row):
                raise ValueError(f"accelerations must be finite, within ±{MAX_ACCEL_MPS2} m/s²")
        return self

    def cell(self, level: int, band: int) -> float | None:
        """The acceleration at ``pedal_pct[level]``, ``speed_mps[band]``; None: not measured."""
        first, row = self.first_level_by_band[band], self.accel_mps2_by_band[band]
        return row[level - first] if first <= level < first + len(row) else None


class PedalsCalibration(_Model):
    throttle: PedalMapTable
    brake: PedalMapTable

    @model_validator(mode="after")
    def _monotonic(self) -> Self:
        for name, table, sign in (("throttle", self.throttle, 1.0), ("brake", self.brake, -1.0)):
            for band, row in enumerate(table.accel_mps2_by_band):
                if any(sign * (b - a) < 0.0 for a, b in itertools.pairwise(row)):
                    direction = "increase" if sign > 0 else "decrease"
                    raise ValueError(
                        f"pedals.{name}: the acceleration must {direction} with the pedal in "
                        f"every band (band {band} at {table.speed_mps[band]} m/s does not)"
                    )
        return self
