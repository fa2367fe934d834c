"""The steering pot's map: raw counts to steering-wheel angle, as an odd polynomial.

``wheel_rad = sum(coeffs[i] * d**(i+1))`` with ``d = counts - centre``: no constant term,
because the centre reading means straight ahead by definition. Evaluating it, its slope
(the calibration file's monotonicity check) and fitting it to measured points are plain
numpy, shared by the file's validation, the daemon's conversions and every maneuver that
measures a map (the pot-map step, and the simulated vehicle's truth fitted the same way).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

# Up to degree 9: the inverse of a pot map with a cubic term near its lock needs it to
# reach a few mrad of steering-wheel angle (degree 5 cannot do better than ~0.02 rad).
MAX_POT_TO_WHEEL_COEFFS = 9


def wheel_rad_at(coeffs: Sequence[float], offset_counts: Any) -> Any:
    """``sum(coeffs[i] * d**(i+1))`` for ``d = offset_counts`` (a float or an array)."""
    return np.polynomial.polynomial.polyval(offset_counts, (0.0, *coeffs))


def wheel_slope_rad_per_count(coeffs: Sequence[float], offset_counts: FloatArray) -> FloatArray:
    """Derivative of :func:`wheel_rad_at` with respect to the counts."""
    derivative = [(i + 1) * c for i, c in enumerate(coeffs)]
    return np.asarray(np.polynomial.polynomial.polyval(offset_counts, derivative), np.float64)


def fit_pot_to_wheel_coeffs(
    offset_counts: FloatArray, wheel_rad: FloatArray, powers: Sequence[int]
) -> tuple[float, ...]:
    """Least squares ``wheel_rad ~ sum(c_p * d**p)`` over ``powers``, as file coefficients.

    Fitted in ``d / max|d|`` (with d**9 of a thousand counts the raw problem is singular),
    then scaled back. Returns ``coeff[i]`` for ``d**(i+1)``, zero where no power was fitted.
    """
    if max(powers) > MAX_POT_TO_WHEEL_COEFFS or min(powers) < 1:
        raise ValueError(f"powers must lie in 1..{MAX_POT_TO_WHEEL_COEFFS} (got {powers})")
    scale = float(np.max(np.abs(offset_counts)))
    design = np.stack([(offset_counts / scale) ** p for p in powers], axis=1)
    scaled, *_ = np.linalg.lstsq(design, wheel_rad, rcond=None)
    coeffs = [0.0] * max(powers)
    for power, coeff in zip(powers, scaled, strict=True):
        coeffs[power - 1] = float(coeff) / scale**power
    return tuple(coeffs)
