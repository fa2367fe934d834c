"""What the palm-tree maneuver records, and its coverage while it runs.

Per GNSS/INS epoch: the time, the position and heading of the reference point (the antenna,
or the anchor, at a known offset from the geometric centre), its speed over ground, the
steering-wheel angle (the pot through the pot map) and the fix's sigma. The recorder shows
the technician how many metres were driven at each held wheel angle, so they know when an
arc is long enough and which half turn comes next; the fit takes the recorded arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from calibration.fit_inputs import (
    FloatArray,
    positive,
    same_length,
    sample_array,
    strictly_increasing,
)


@dataclass(frozen=True)
class PalmTreeSamples:
    """One array per quantity, one entry per epoch, in time order. Checked on creation."""

    t_s: FloatArray
    x_m: FloatArray  # reference point, local east
    y_m: FloatArray  # reference point, local north
    heading_rad: FloatArray  # the vehicle's heading (yaw), not the course over ground
    speed_mps: FloatArray  # the reference point's speed over ground (sign ignored)
    wheel_rad: FloatArray  # steering-wheel angle, left positive
    fix_sigma_m: FloatArray  # the fix's 1-sigma horizontal error

    def __post_init__(self) -> None:
        checked = {f.name: sample_array(f.name, getattr(self, f.name)) for f in fields(self)}
        same_length(checked)
        strictly_increasing("t_s", checked["t_s"])
        if np.any(checked["fix_sigma_m"] < 0.0):
            raise ValueError("fix_sigma_m must not be negative")
        for name, array in checked.items():
            object.__setattr__(self, name, array)

    def __len__(self) -> int:
        return int(self.t_s.size)


class PalmTreeRecorder:
    """Collects epochs as they arrive and the distance driven per wheel-angle bin.

    Bins are ``bin_width_rad`` wide and centred on its multiples (half turns by default,
    the paper's step between arcs). Distance is speed times time between epochs, so a GNSS
    jump does not count as driving.
    """

    def __init__(self, bin_width_rad: float = math.pi) -> None:
        positive("bin_width_rad", bin_width_rad)
        self._bin_width_rad = bin_width_rad
        self._columns: dict[str, list[float]] = {f.name: [] for f in fields(PalmTreeSamples)}
        self._coverage_m: dict[int, float] = {}

    def reset(self) -> None:
        for column in self._columns.values():
            column.clear()
        self._coverage_m.clear()

    def update(
        self,
        t_s: float,
        x_m: float,
        y_m: float,
        heading_rad: float,
        speed_mps: float,
        wheel_rad: float,
        fix_sigma_m: float,
    ) -> None:
        """Add one epoch; ValueError for a non-finite value or a time not after the last."""
        values = (t_s, x_m, y_m, heading_rad, speed_mps, wheel_rad, fix_sigma_m)
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"epoch with a non-finite value: {values}")
        times = self._columns["t_s"]
        if times and t_s <= times[-1]:
            raise ValueError(f"epoch at {t_s} s is not after the last one at {times[-1]} s")
        if times:
            dt_s = t_s - times[-1]
            speed = 0.5 * (abs(speed_mps) + abs(self._columns["speed_mps"][-1]))
            key = round(wheel_rad / self._bin_width_rad)
            self._coverage_m[key] = self._coverage_m.get(key, 0.0) + speed * dt_s
        for name, value in zip(self._columns, values, strict=True):
            self._columns[name].append(value)

    def coverage_m(self) -> dict[float, float]:
        """Bin centre (wheel rad) -> metres driven there, in wheel-angle order."""
        return {
            key * self._bin_width_rad: metres for key, metres in sorted(self._coverage_m.items())
        }

    def samples(self) -> PalmTreeSamples:
        return PalmTreeSamples(**{name: np.array(v) for name, v in self._columns.items()})
