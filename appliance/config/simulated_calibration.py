"""The built-in simulated vehicle's calibration: its true pot mapping, fitted.

The steering twin reports pot counts through a known mapping (:class:`PotMapping`). The
calibration file stores the inverse, counts to steering-wheel angle, as a polynomial;
the inverse of a cubic is not a polynomial, so it is fitted, exactly as a calibration
maneuver fits measured points, and ``source`` says so rather than claiming a measurement.
"""

from __future__ import annotations

import math
from dataclasses import replace
from datetime import UTC, datetime

import numpy as np

from appliance.config.calibration import (
    POT_FULL_SCALE_COUNTS,
    CalibrationFile,
    SteeringCalibration,
)
from calibration.pot_map import fit_pot_to_wheel_coeffs
from drivers.actuators.steering_model import PotMapping, ServoParams

# Readings this far past the steering lock are still accepted: the pot's noise at the
# lock (0.8 counts rms) must not look like a broken pot. 0.05 rad is ~4 counts there.
VALID_RANGE_MARGIN_RAD = 0.05
# The inverse of the twin's cubic is odd; degree 9 is the lowest odd degree whose least
# squares fit stays within a few mrad of steering-wheel angle up to the lock.
FIT_POWERS = (1, 3, 5, 7, 9)
FIT_SAMPLES = 801

DEFAULT_MAPPING = PotMapping()
DEFAULT_SERVO = ServoParams()


def simulated_calibration(
    vehicle_name: str,
    mapping: PotMapping = DEFAULT_MAPPING,
    servo: ServoParams = DEFAULT_SERVO,
    created_utc: datetime | None = None,
) -> CalibrationFile:
    """The calibration of the simulated vehicle whose pot and servo are ``mapping`` and
    ``servo``, named ``vehicle_name``. ``created_utc`` defaults to now."""
    reach_rad = servo.wheel_limit_rad + VALID_RANGE_MARGIN_RAD
    wheel_rad = np.linspace(-reach_rad, reach_rad, FIT_SAMPLES)
    counts = np.array([mapping.ideal_counts(float(w)) for w in wheel_rad])
    coeffs = fit_pot_to_wheel_coeffs(counts - mapping.centre_counts, wheel_rad, FIT_POWERS)
    ends = (mapping.ideal_counts(-reach_rad), mapping.ideal_counts(reach_rad))
    valid_min = max(0, math.floor(min(ends)))
    valid_max = min(POT_FULL_SCALE_COUNTS, math.ceil(max(ends)))
    if created_utc is None:
        created_utc = datetime.now(UTC).replace(microsecond=0)
    source = (
        "the simulated vehicle's true mapping (drivers.actuators.steering_model.PotMapping: "
        f"centre {mapping.centre_counts} counts, {mapping.gain_counts_per_rad} counts/rad, "
        f"{mapping.cubic_counts_per_rad3} counts/rad^3), fitted: odd least squares of "
        f"degree {max(FIT_POWERS)} over +-{reach_rad:.3f} rad of steering-wheel angle; "
        "not a measurement"
    )
    return CalibrationFile(
        vehicle_name=vehicle_name,
        created_utc=created_utc,
        source=source,
        steering=SteeringCalibration(
            pot_centre_counts=float(mapping.centre_counts),
            pot_to_wheel_coeffs=coeffs,
            pot_valid_min_counts=valid_min,
            pot_valid_max_counts=valid_max,
            steering_ratio=float(servo.steering_ratio),
        ),
    )


def servo_of(steering_ratio: float) -> ServoParams:
    """The simulated servo with the vehicle file's ``simulation.steering.steering_ratio``."""
    return replace(DEFAULT_SERVO, steering_ratio=steering_ratio)
