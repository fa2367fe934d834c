"""A steering wish the kit's servo can follow, and a speed that waits for the wheels.

A guidance law asks for an angle now; the servo turns the wheels at a finite rate and
with a lag, and the safety layer faults the steering when it falls more than a few
degrees behind its command for half a second. So the wish moves towards what the law
wants at a rate the servo follows within that tolerance (lag x rate < tolerance), from
the measured angle when automatic control begins; and the vehicle drives at the law's
speed only as far as the wheels are where the law wants them: standing until they are
within ``wait_rad``, full speed when they are there. A planned arc assumes its wheels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class WheelFollowParams:
    rate_rad_per_s: float
    wait_rad: float = math.radians(6.0)


class WheelFollower:
    """``update(wanted, measured, t) -> (wish, speed share)``; `reset` when released."""

    def __init__(self, params: WheelFollowParams) -> None:
        if not (params.rate_rad_per_s > 0.0 and params.wait_rad > 0.0):
            raise ValueError("the rate and the wait must be positive")
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._wish_rad: float | None = None
        self._t_s = 0.0

    def update(
        self, wanted_rad: float, measured_rad: float | None, t_s: float
    ) -> tuple[float, float]:
        seen = measured_rad is not None and math.isfinite(measured_rad)
        last = self._wish_rad
        if last is None or not math.isfinite(last):
            last = measured_rad if seen and measured_rad is not None else 0.0
            self._t_s = t_s
        if not math.isfinite(wanted_rad):
            wanted_rad = last
        step = self.params.rate_rad_per_s * max(0.0, t_s - self._t_s) if math.isfinite(t_s) else 0.0
        wish = last + max(-step, min(step, wanted_rad - last))
        self._wish_rad = wish
        if math.isfinite(t_s):
            self._t_s = t_s
        if not seen or measured_rad is None:
            return wish, 0.0
        return wish, max(0.0, 1.0 - abs(wanted_rad - measured_rad) / self.params.wait_rad)
