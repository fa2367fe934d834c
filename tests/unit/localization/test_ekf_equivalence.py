"""The filter's shortcuts give what the long way gives.

The association works each innovation out once (``update_nearest_cylinder``) and hands
its prediction and Jacobian to the update: that is the long way to the last bit. The
algebra in floats (the NIS, the update, the board motion's fusion) is numpy's and
filterpy's to rounding, and the board's motion keeps each scanner's window's figures
until the window changes.
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from appliance.localization.board_motion import (
    BoardMotion,
    BoardMotionParams,
    BoardSighting,
    motion_between,
)
from appliance.localization.compound import wrap_angle_rad
from appliance.localization.launcher_ekf import (
    LauncherEkf,
    cylinder_measurement,
)
from appliance.localization.launcher_map import LauncherMap
from drivers.geometry import Pose2D
from tests.unit.localization.synthetic import CYL_COV, SENSORS, approach

LANDMARKS = [(landmark.x_m, landmark.y_m) for landmark in LauncherMap().cylinders]


def _filter() -> LauncherEkf:
    ekf = LauncherEkf()
    ekf.reset(Pose2D(-9.0, 0.2, 0.03), np.diag([0.01, 0.01, 0.001]), t_s=0.0)
    return ekf


@pytest.mark.parametrize("sensor", sorted(SENSORS))
@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.02, 0.004), (0.3, 0.05), (-4.0, 1.0)])
def test_update_nearest_cylinder_is_choosing_by_innovation_then_updating(
    sensor: str, offset: tuple[float, float]
) -> None:
    mine, theirs = _filter(), _filter()
    z, _ = cylinder_measurement(mine.state, LANDMARKS[0], SENSORS[sensor])
    z = z + np.array(offset)
    r_cov = CYL_COV + np.diag([1e-5, 1e-7])
    index, outcome = mine.update_nearest_cylinder(z, r_cov, LANDMARKS, SENSORS[sensor])
    best = min(LANDMARKS, key=lambda xy: theirs.innovation(z, r_cov, xy, SENSORS[sensor]))
    expected = theirs.update_cylinder(z, r_cov, best, SENSORS[sensor])
    assert LANDMARKS[index] == best
    assert outcome == expected
    assert mine.state.tobytes() == theirs.state.tobytes()
    assert mine.covariance.tobytes() == theirs.covariance.tobytes()
    assert (mine.accepted, mine.rejected) == (theirs.accepted, theirs.rejected)


def _fused_from_scratch(
    history: dict[str, list[BoardSighting]], now_s: float, params: BoardMotionParams
) -> tuple[np.ndarray, np.ndarray] | None:
    """``BoardMotion.motion`` as it was before it kept anything: every window's motion
    worked out again, every inverse taken twice."""
    estimates = []
    for sightings in history.values():
        if len(sightings) < 2 or now_s - sightings[-1].t_s > params.max_age_s:
            continue
        if sightings[-1].t_s - sightings[0].t_s > params.max_age_s:
            continue
        found = motion_between(sightings[0], sightings[-1], params)
        if found is not None:
            estimates.append(found)
    if not estimates:
        return None
    if len(estimates) == 1:
        return estimates[0].velocity, estimates[0].covariance
    information = sum(np.linalg.inv(e.covariance) for e in estimates)
    covariance = np.linalg.inv(information)
    weighted = sum(np.linalg.inv(e.covariance) @ e.velocity for e in estimates)
    return covariance @ weighted, covariance


def test_board_motion_kept_per_window_is_the_motion_worked_out_afresh() -> None:
    """Each window's motion kept, and the fusion, are what working everything out again
    with numpy gives."""
    samples = approach(np.random.default_rng(7), LauncherMap(), duration_s=4.0)
    motion = BoardMotion()
    for sample in samples:
        motion.update(sample.sensor, sample.board)
        for now_s in (sample.t_s, sample.t_s + 0.02, sample.t_s + 0.6):
            found = motion.motion(now_s)
            history = {name: list(window) for name, window in motion._history.items()}
            expected = _fused_from_scratch(history, now_s, motion.params)
            if expected is None:
                assert found is None
                continue
            assert found is not None
            # The fusion is in floats (cofactor inverses), numpy's inverses here: to
            # rounding, 1e-9 of the largest entry.
            for got, want in zip((found.velocity, found.covariance), expected, strict=True):
                assert np.abs(got - want).max() <= 1e-9 * np.abs(want).max()


def _residual(z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
    return np.array([z[0] - z_hat[0], wrap_angle_rad(float(z[1] - z_hat[1]))])


@pytest.mark.parametrize("sensor", sorted(SENSORS))
@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.02, 0.004), (-0.05, 0.01)])
def test_an_update_is_filterpys_to_rounding(sensor: str, offset: tuple[float, float]) -> None:
    """The update, in floats, is filterpy's ``ExtendedKalmanFilter.update`` (the Joseph
    form, numpy's products and inverse) with the model evaluated where filterpy asks, to
    1e-12 relative (of the covariance's largest entry for the covariance)."""
    mine = _filter()
    kf = ExtendedKalmanFilter(dim_x=3, dim_z=2)
    kf.x, kf.P = mine.state, mine.covariance
    z, _ = cylinder_measurement(mine.state, LANDMARKS[0], SENSORS[sensor])
    z = z + np.array(offset)
    assert mine.update_cylinder(z, CYL_COV, LANDMARKS[0], SENSORS[sensor]).accepted

    def model(state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return cylinder_measurement(state, LANDMARKS[0], SENSORS[sensor])

    kf.update(z, lambda s: model(s)[1], lambda s: model(s)[0], R=CYL_COV, residual=_residual)
    x = np.array(kf.x, dtype=float)
    x[2] = wrap_angle_rad(float(x[2]))
    p = 0.5 * (kf.P + kf.P.T)
    assert mine.state == pytest.approx(x, rel=1e-12, abs=1e-15)
    assert np.abs(mine.covariance - p).max() <= 1e-12 * np.abs(p).max()


@pytest.mark.parametrize("sensor", sorted(SENSORS))
def test_the_nis_is_numpys_to_rounding(sensor: str) -> None:
    """The NIS is worked out in floats (2x2 and 2x3 matrices); numpy's products and solve
    give it to rounding."""
    ekf = _filter()
    rng = np.random.default_rng(3)
    for landmark in LANDMARKS:
        z_hat, h = cylinder_measurement(ekf.state, landmark, SENSORS[sensor])
        for _ in range(20):
            z = z_hat + rng.normal(0.0, [0.05, 0.02])
            r_cov = CYL_COV * rng.uniform(0.5, 2.0)
            y = np.array([z[0] - z_hat[0], wrap_angle_rad(float(z[1] - z_hat[1]))])
            expected = float(y @ np.linalg.solve(h @ ekf.covariance @ h.T + r_cov, y))
            got = ekf.innovation(z, r_cov, landmark, SENSORS[sensor])
            assert got == pytest.approx(expected, rel=1e-12)
