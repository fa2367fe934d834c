"""The simulated steering linkage: steering-wheel angle to front tyre angle.

A real linkage is not a constant ratio: the steering arms' geometry makes the tyre turn a
little more (or less) per wheel turn towards the lock, which is what the palm tree
(Stanley et al., Fig. 19) measures. The simulator models it as the constant ratio plus a
cubic term scaled to the lock, ``tyre = wheel / ratio * (1 + cubic * (wheel / lock)**2)``,
so ``cubic = 0.06`` turns the tyre 6 % further than the ratio alone at the lock. The
daemon is never told ``cubic``: the built-in calibration assumes the constant ratio, as
a vehicle file does before its palm tree.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SteeringLinkage:
    steering_ratio: float  # wheel rad per tyre rad about straight ahead
    lock_wheel_rad: float  # the wheel angle at the lock, where the cubic term is ``cubic``
    cubic: float = 0.0

    def __post_init__(self) -> None:
        if not self.steering_ratio > 0.0 or not self.lock_wheel_rad > 0.0:
            raise ValueError("the steering ratio and the lock must be positive")
        # Monotonic up to the lock: d tyre / d wheel = (1 + 3 cubic x^2) / ratio > 0.
        if not -1.0 / 3.0 < self.cubic < 1.0:
            raise ValueError(f"cubic {self.cubic} makes the linkage fold back before the lock")

    def tyre_rad(self, wheel_rad: float) -> float:
        x = wheel_rad / self.lock_wheel_rad
        return wheel_rad / self.steering_ratio * (1.0 + self.cubic * x * x)
