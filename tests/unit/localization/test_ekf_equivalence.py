"""The filter's shortcuts give what the long way gives, to the last bit.

The association works each innovation out once (``update_nearest_cylinder``), and the
board's motion keeps each
scanner's window's figures until the window changes: a docking simulation's results
must not move by a bit for any of it.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.localization.board_motion import (
    BoardMotion,
    BoardMotionParams,
    BoardSighting,
    motion_between,
)
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
            assert found.velocity.tobytes() == expected[0].tobytes()
            assert found.covariance.tobytes() == expected[1].tobytes()
