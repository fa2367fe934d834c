"""The simulated vehicle's calibration reproduces the steering twin's true mapping."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from appliance.config.calibration import Calibration
from appliance.config.calibration_file import read_calibration_file, write_calibration
from appliance.config.simulated_calibration import VALID_RANGE_MARGIN_RAD, simulated_calibration
from calibration.pot_map import fit_pot_to_wheel_coeffs
from drivers.actuators.steering_model import PotMapping, ServoParams, pot_counts

WHEEL_TOLERANCE_RAD = 0.005
TYRE_TOLERANCE_DEG = 0.05


def whole_range_rad(servo: ServoParams) -> list[float]:
    return [float(w) for w in np.linspace(-servo.wheel_limit_rad, servo.wheel_limit_rad, 2001)]


def slope_counts_per_rad(mapping: PotMapping, wheel_rad: float) -> float:
    return abs(mapping.gain_counts_per_rad + 3.0 * mapping.cubic_counts_per_rad3 * wheel_rad**2)


CASES = [
    pytest.param(PotMapping(), ServoParams(), id="the-twin"),
    # the pot mounted the other way round: counts fall as the wheel turns left
    pytest.param(
        PotMapping(gain_counts_per_rad=-180.0, cubic_counts_per_rad3=0.35),
        ServoParams(),
        id="decreasing",
    ),
    pytest.param(
        PotMapping(centre_counts=1900.0, gain_counts_per_rad=210.0, cubic_counts_per_rad3=-0.2),
        ServoParams(steering_ratio=20.0, wheel_limit_rad=8.0),
        id="another-vehicle",
    ),
]


@pytest.mark.parametrize(("mapping", "servo"), CASES)
def test_fit_reproduces_the_true_wheel_angle(mapping: PotMapping, servo: ServoParams) -> None:
    cal = Calibration.from_file(simulated_calibration("sim", mapping, servo))
    worst_rad = 0.0
    for wheel_rad in whole_range_rad(servo):
        estimate = cal.wheel_rad_from_counts(mapping.ideal_counts(wheel_rad))
        assert estimate is not None, f"reading at {wheel_rad} rad refused"
        worst_rad = max(worst_rad, abs(estimate - wheel_rad))
    assert worst_rad < WHEEL_TOLERANCE_RAD


@pytest.mark.parametrize(("mapping", "servo"), CASES)
def test_fit_reproduces_the_tyre_angle_from_noiseless_pot_readings(
    mapping: PotMapping, servo: ServoParams
) -> None:
    cal = Calibration.from_file(simulated_calibration("sim", mapping, servo))
    for wheel_rad in whole_range_rad(servo):
        counts = pot_counts(wheel_rad, mapping)  # rounded to whole counts, as the ADC does
        tyre_rad = cal.tyre_rad_from_counts(counts)
        assert tyre_rad is not None
        assert math.degrees(abs(tyre_rad - wheel_rad / servo.steering_ratio)) < TYRE_TOLERANCE_DEG
        # in steering-wheel angle the fit's error adds to half a count of rounding, which
        # near the lock (87 counts/rad) is itself 0.006 rad: no map can do better than that
        rounding_rad = 0.5 / slope_counts_per_rad(mapping, wheel_rad)
        wheel_estimate = cal.wheel_rad_from_counts(counts)
        assert wheel_estimate is not None
        assert abs(wheel_estimate - wheel_rad) < WHEEL_TOLERANCE_RAD + rounding_rad


def test_a_cubic_fit_would_not_be_good_enough() -> None:
    """Why the fit goes to degree 9: the inverse of the twin's cubic is far from a cubic."""
    mapping, servo = PotMapping(), ServoParams()
    wheel_rad = np.linspace(-servo.wheel_limit_rad, servo.wheel_limit_rad, 801)
    counts = np.array([mapping.ideal_counts(float(w)) for w in wheel_rad])
    offsets = counts - mapping.centre_counts
    for powers, good_enough in (((1, 3), False), ((1, 3, 5), False), ((1, 3, 5, 7, 9), True)):
        coeffs = fit_pot_to_wheel_coeffs(offsets, wheel_rad, powers)
        estimate = np.polynomial.polynomial.polyval(offsets, (0.0, *coeffs))
        worst_rad = float(np.max(np.abs(estimate - wheel_rad)))
        assert (worst_rad < WHEEL_TOLERANCE_RAD) is good_enough, (powers, worst_rad)


def test_valid_range_covers_the_lock_and_noise_but_not_beyond() -> None:
    mapping, servo = PotMapping(), ServoParams()
    cal = Calibration.from_file(simulated_calibration("sim", mapping, servo))
    noise_counts = 4.0 * mapping.noise_counts  # four sigma past the lock is still a good pot
    for lock_rad, outward in ((servo.wheel_limit_rad, 1.0), (-servo.wheel_limit_rad, -1.0)):
        at_lock = mapping.ideal_counts(lock_rad) + outward * noise_counts
        assert cal.wheel_rad_from_counts(at_lock) is not None
        beyond = mapping.ideal_counts(lock_rad + outward * 4 * VALID_RANGE_MARGIN_RAD)
        assert cal.wheel_rad_from_counts(beyond) is None
    low_deg, high_deg = (math.degrees(end) for end in cal.valid_tyre_range_rad)
    assert 30.0 < high_deg < 30.3
    assert -30.3 < low_deg < -30.0


def test_valid_range_is_clipped_to_the_adc() -> None:
    hot = PotMapping(gain_counts_per_rad=250.0)  # reaches 4201 counts at the lock
    model = simulated_calibration("sim", hot)
    assert model.steering.pot_valid_max_counts == 4095
    assert model.steering.pot_valid_min_counts > 0


def test_source_tells_the_truth_about_provenance() -> None:
    source = simulated_calibration("sim").source
    assert "simulated vehicle's true mapping" in source
    assert "fitted" in source
    assert "not a measurement" in source


def test_creation_time_is_an_argument() -> None:
    when = datetime(2026, 12, 1, 15, tzinfo=UTC)
    assert simulated_calibration("sim", created_utc=when).created_utc == when
    now = simulated_calibration("sim").created_utc
    assert abs(now - datetime.now(UTC)) < timedelta(seconds=5)


def test_simulated_calibration_writes_and_loads_back(tmp_path: Path) -> None:
    model = simulated_calibration("bench")
    write_calibration(tmp_path / "cal.toml", model)
    assert read_calibration_file(tmp_path / "cal.toml", "bench") == model


def test_fit_refuses_powers_the_file_cannot_hold() -> None:
    offsets = np.linspace(-1000.0, 1000.0, 11)
    with pytest.raises(ValueError, match="powers"):
        fit_pot_to_wheel_coeffs(offsets, offsets * 0.005, (1, 11))
