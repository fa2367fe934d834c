"""The steering-wheel angle to front tyre angle map (Stanley et al., Fig. 19).

A steering linkage is not a constant ratio: the tyre angle per wheel turn changes towards
the lock (their eq. 4 is an arcsine of a sine). So the map is a polynomial in the wheel
angle without a constant term, ``tyre = sum(c_p w^p)``, because the pot map already defines
the wheel angle as zero where the vehicle runs straight; odd powers by default, since a
linkage mirrored left and right gives an odd function, with even powers on request for one
that is not. A polynomial rather than a spline because the palm tree gives one point per
held wheel angle (seven, at half turns) and a spline through seven noisy points would
follow their noise. A map is only usable when it is
strictly monotonic over the wheel angles it was measured on (one tyre angle per wheel angle
and back), which :attr:`TyreMapFit.monotonic` reports; outside that range it is not
trusted at all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from calibration.fit_inputs import FloatArray, same_length, sample_array

MONOTONIC_CHECK_POINTS = 401
# Floor of each point's sigma in the weights: the polynomial's own misfit of a linkage is
# of this order, and without it one very precise arc would dictate the whole curve.
DEFAULT_SIGMA_FLOOR_RAD = math.radians(0.05)


@dataclass(frozen=True)
class TyreMap:
    """``tyre_rad = sum(coeffs[i] * wheel_rad**(i+1))``, trusted on [wheel_min, wheel_max]."""

    coeffs: tuple[float, ...]
    wheel_min_rad: float
    wheel_max_rad: float

    def tyre_rad(self, wheel_rad: Any) -> Any:
        """The front tyre angle at ``wheel_rad`` (a float or an array)."""
        return np.polynomial.polynomial.polyval(wheel_rad, (0.0, *self.coeffs))

    def slope(self, wheel_rad: Any) -> Any:
        """Tyre radians per wheel radian at ``wheel_rad``."""
        derivative = [(i + 1) * c for i, c in enumerate(self.coeffs)]
        return np.polynomial.polynomial.polyval(wheel_rad, derivative)

    @property
    def centre_ratio(self) -> float:
        """Wheel radians per tyre radian at straight ahead: the ratio a linear map would use
        (the steering model's ``steering_ratio``), for comparison only."""
        return math.inf if self.coeffs[0] == 0.0 else 1.0 / self.coeffs[0]

    def is_monotonic(self) -> bool:
        grid = np.linspace(self.wheel_min_rad, self.wheel_max_rad, MONOTONIC_CHECK_POINTS)
        signs = np.sign(self.slope(grid))
        return bool(np.all(signs == signs[0]) and signs[0] != 0.0)


@dataclass(frozen=True)
class TyreMapFit:
    tyre_map: TyreMap
    powers: tuple[int, ...]
    residuals_rad: FloatArray  # measured minus mapped, per point
    residual_rms_deg: float
    residual_max_deg: float
    monotonic: bool
    method: str


def fit_tyre_map(
    wheel_rad: npt.ArrayLike,
    tyre_rad: npt.ArrayLike,
    tyre_sigma_rad: npt.ArrayLike,
    *,
    powers: Sequence[int] = (1, 3, 5),
    sigma_floor_rad: float = DEFAULT_SIGMA_FLOOR_RAD,
) -> TyreMapFit:
    """Weighted least squares of the polynomial through measured (wheel, tyre) points.

    Weights are ``1 / (sigma² + floor²)`` (see ``DEFAULT_SIGMA_FLOOR_RAD``). Fitted in
    ``w / max|w|`` for conditioning. ValueError for repeated or non-positive powers, fewer points
    than powers + 1 (no residual left to judge the fit by) or non-finite input.
    """
    powers = tuple(powers)
    if not powers or min(powers) < 1 or len(set(powers)) != len(powers):
        raise ValueError(f"powers must be distinct positive integers (got {powers})")
    need = len(powers) + 1
    wheel = sample_array("wheel_rad", wheel_rad, min_samples=need)
    tyre = sample_array("tyre_rad", tyre_rad, min_samples=need)
    sigma = sample_array("tyre_sigma_rad", tyre_sigma_rad, min_samples=need)
    same_length({"wheel_rad": wheel, "tyre_rad": tyre, "tyre_sigma_rad": sigma})
    if np.any(sigma < 0.0):
        raise ValueError("tyre_sigma_rad must not be negative")
    scale = float(np.max(np.abs(wheel)))
    if scale == 0.0:
        raise ValueError("all wheel angles are zero: the map needs points off centre")
    weight_sqrt = 1.0 / np.sqrt(sigma**2 + sigma_floor_rad**2)
    design = np.stack([(wheel / scale) ** p for p in powers], axis=1)
    scaled, *_ = np.linalg.lstsq(design * weight_sqrt[:, None], tyre * weight_sqrt, rcond=None)
    coeffs = [0.0] * max(powers)
    for power, coeff in zip(powers, scaled, strict=True):
        coeffs[power - 1] = float(coeff) / scale**power
    tyre_map = TyreMap(tuple(coeffs), float(np.min(wheel)), float(np.max(wheel)))
    residuals = tyre - np.asarray(tyre_map.tyre_rad(wheel), dtype=np.float64)
    return TyreMapFit(
        tyre_map=tyre_map,
        powers=powers,
        residuals_rad=residuals,
        residual_rms_deg=math.degrees(float(np.sqrt(np.mean(residuals**2)))),
        residual_max_deg=math.degrees(float(np.max(np.abs(residuals)))),
        monotonic=tyre_map.is_monotonic(),
        method=f"weighted least squares, polynomial of powers {powers} without a constant",
    )
