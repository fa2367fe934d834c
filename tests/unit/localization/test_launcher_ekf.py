"""The launcher EKF against independent computations, and its consistency by Monte Carlo."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import chi2

from appliance.localization.board_motion import BoardMotion
from appliance.localization.compound import (
    compound,
    compound_jacobians,
    inverse,
    relative,
    wrap_angle_rad,
)
from appliance.localization.launcher_ekf import (
    BodyMotion,
    EkfParams,
    LauncherEkf,
    board_measurement,
    cylinder_measurement,
)
from appliance.localization.launcher_map import LauncherMap
from drivers.geometry import Pose2D
from tests.unit.localization.synthetic import CYL_COV, LINE_COV, SENSORS, approach

angles = st.floats(-math.pi, math.pi)
coords = st.floats(-20.0, 20.0)


@given(coords, coords, angles, coords, coords, angles)
def test_compound_matches_the_drivers_pose_type(
    x: float, y: float, a: float, dx: float, dy: float, da: float
) -> None:
    mine = compound(np.array([x, y, a]), np.array([dx, dy, da]))
    theirs = Pose2D(x, y, a).compose(Pose2D(dx, dy, da))
    assert mine[:2] == pytest.approx(theirs[:2], abs=1e-9)
    assert wrap_angle_rad(float(mine[2] - theirs.yaw_rad)) == pytest.approx(0.0, abs=1e-12)


@given(coords, coords, angles)
def test_inverse_undoes_compound(x: float, y: float, a: float) -> None:
    pose = np.array([x, y, a])
    assert compound(pose, inverse(pose)) == pytest.approx(np.zeros(3), abs=1e-9)
    assert relative(pose, pose) == pytest.approx(np.zeros(3), abs=1e-9)


def _numeric_jacobian(
    function: Callable[[np.ndarray], np.ndarray], point: np.ndarray, wrap_rows: tuple[int, ...]
) -> np.ndarray:
    eps = 1e-6
    columns = []
    for i in range(point.size):
        step = np.zeros(point.size)
        step[i] = eps
        diff = function(point + step) - function(point - step)
        for row in wrap_rows:
            diff[row] = wrap_angle_rad(float(diff[row]))
        columns.append(diff / (2 * eps))
    return np.column_stack(columns)


@given(coords, coords, angles, coords, coords, angles)
def test_compound_jacobians_match_finite_differences(
    x: float, y: float, a: float, dx: float, dy: float, da: float
) -> None:
    pose, delta = np.array([x, y, a]), np.array([dx, dy, da])
    j_pose, j_delta = compound_jacobians(pose, delta)
    assert j_pose == pytest.approx(
        _numeric_jacobian(lambda p: compound(p, delta), pose, (2,)), abs=1e-5
    )
    assert j_delta == pytest.approx(
        _numeric_jacobian(lambda d: compound(pose, d), delta, (2,)), abs=1e-5
    )


@given(
    st.floats(-15.0, -1.0),
    st.floats(-3.0, 3.0),
    angles,
    st.sampled_from(sorted(SENSORS)),
)
def test_cylinder_jacobian_matches_finite_differences(
    x: float, y: float, a: float, sensor: str
) -> None:
    landmark = (-0.5, 2.5)
    state = np.array([x, y, a])
    z, jac = cylinder_measurement(state, landmark, SENSORS[sensor])
    numeric = _numeric_jacobian(
        lambda s: cylinder_measurement(s, landmark, SENSORS[sensor])[0], state, (1,)
    )
    assert jac == pytest.approx(numeric, abs=1e-5)
    # and the value itself, from the geometry written out another way
    sensor_world = Pose2D(x, y, a).compose(SENSORS[sensor])
    assert z[0] == pytest.approx(math.dist(sensor_world[:2], landmark), abs=1e-9)


def test_board_update_is_the_textbook_kalman_update() -> None:
    """The board measurement is linear, so one update must equal the plain equations
    (with the Joseph form, which for the optimal gain equals (I - KH)P)."""
    ekf = LauncherEkf()
    prior = np.diag([0.04, 0.09, 0.001])
    prior[0, 2] = prior[2, 0] = 0.002
    ekf.reset(Pose2D(-8.0, 0.3, 0.02), prior, t_s=0.0)
    z = np.array([8.05, -0.025])
    r_cov = np.diag([1e-4, 1e-6])
    outcome = ekf.update_board(z, r_cov)
    assert outcome.accepted
    h = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    x0 = np.array([-8.0, 0.3, 0.02])
    s = h @ prior @ h.T + r_cov
    k = prior @ h.T @ np.linalg.inv(s)
    expected_x = x0 + k @ (z - h @ x0)
    expected_p = (np.eye(3) - k @ h) @ prior
    assert ekf.state == pytest.approx(expected_x, abs=1e-12)
    assert ekf.covariance == pytest.approx(expected_p, abs=1e-12)
    y = z - h @ x0
    assert outcome.nis == pytest.approx(float(y @ np.linalg.inv(s) @ y), rel=1e-9)


def test_a_false_cylinder_is_gated_and_counted() -> None:
    ekf = LauncherEkf()
    ekf.reset(Pose2D(-8.0, 0.0, 0.0), np.diag([1e-4, 1e-4, 1e-6]), t_s=0.0)
    landmark = (-0.5, 2.5)
    z, _ = cylinder_measurement(ekf.state, landmark, SENSORS["left"])
    before = ekf.state
    # a post 0.4 m beside the landmark, taken for it
    outcome = ekf.update_cylinder(z + np.array([0.0, 0.05]), CYL_COV, landmark, SENSORS["left"])
    assert not outcome.accepted
    assert outcome.nis > chi2.ppf(0.999, 2)
    assert ekf.rejected["cylinder"] == 1
    assert ekf.state == pytest.approx(before, abs=0.0)
    assert ekf.update_cylinder(z, CYL_COV, landmark, SENSORS["left"]).accepted


def test_a_long_run_of_rejections_inflates_rather_than_locks_out() -> None:
    params = EkfParams(inflate_after_rejections=5)
    ekf = LauncherEkf(params)
    # The filter is sure, and wrong by 0.3 m: every measurement looks like an outlier.
    ekf.reset(Pose2D(-8.0, 0.3, 0.0), np.diag([1e-6, 1e-6, 1e-8]), t_s=0.0)
    truth = np.array([-8.0, 0.0, 0.0])
    landmark = (-0.5, 2.5)
    z, _ = cylinder_measurement(truth, landmark, SENSORS["left"])
    outcomes = [ekf.update_cylinder(z, CYL_COV, landmark, SENSORS["left"]) for _ in range(40)]
    assert not outcomes[0].accepted
    assert ekf.inflations >= 1
    assert any(o.accepted for o in outcomes)
    assert abs(ekf.state[1]) < 0.15  # from 0.3: the measurements are being heard again


def test_an_old_measurement_is_refused_and_changes_nothing() -> None:
    ekf = LauncherEkf()
    ekf.reset(Pose2D(-8.0, 0.0, 0.0), np.eye(3) * 1e-3, t_s=10.0)
    assert ekf.predict(10.1, BodyMotion.still())
    before_x, before_p = ekf.state, ekf.covariance
    assert not ekf.predict(10.0, BodyMotion.still())
    assert ekf.rejected["out_of_order"] == 1
    assert ekf.state == pytest.approx(before_x, abs=0.0)
    assert ekf.covariance == pytest.approx(before_p, abs=0.0)


def test_a_malformed_measurement_is_refused() -> None:
    ekf = LauncherEkf()
    ekf.reset(Pose2D(-8.0, 0.0, 0.0), np.eye(3) * 1e-3, t_s=0.0)
    outcome = ekf.update_board(np.array([math.nan, 0.0]), LINE_COV)
    assert not outcome.accepted and "malformed" in outcome.reason


def _run_filter(seed: int, launcher: LauncherMap) -> tuple[np.ndarray, np.ndarray]:
    """NEES per sample of one approach, and the final estimate error."""
    rng = np.random.default_rng(seed)
    samples = approach(rng, launcher, duration_s=12.0)
    first = samples[0]
    p0 = np.diag([0.05**2, 0.05**2, math.radians(0.5) ** 2])
    start = first.truth + rng.multivariate_normal(np.zeros(3), p0)
    ekf = LauncherEkf()
    ekf.reset(Pose2D(*start), p0, t_s=first.t_s)
    motion = BoardMotion()
    nees = []
    for sample in samples:
        motion.update(sample.sensor, sample.board)
        ekf.predict(sample.t_s, motion.motion(sample.t_s) or BodyMotion.still())
        for z, landmark in sample.cylinders:
            ekf.update_cylinder(z, CYL_COV, landmark, SENSORS[sample.sensor])
        ekf.update_board(np.array([sample.board.r_m, sample.board.alpha_rad]), LINE_COV)
        error = ekf.state - sample.truth
        error[2] = wrap_angle_rad(float(error[2]))
        nees.append(float(error @ np.linalg.solve(ekf.covariance, error)))
    return np.array(nees), error


def test_the_filter_is_consistent_over_monte_carlo_runs() -> None:
    """Bar-Shalom's test: the NEES averaged over N runs lies inside the two-sided 95 %
    band of χ²(3N)/N, on the whole and at most steps. Fixed seeds, so the verdict is
    reproducible. (The filter is on the cautious side, about 2.5 against 3: the board's
    velocity is taken to keep its error for its whole window, see ``BodyMotion``.)"""
    launcher = LauncherMap()
    runs = 16
    per_run = [_run_filter(seed, launcher)[0] for seed in range(runs)]
    steps = min(len(r) for r in per_run)
    mean_nees = np.mean([r[:steps] for r in per_run], axis=0)
    low, high = chi2.ppf([0.025, 0.975], 3 * runs) / runs
    inside = np.mean((mean_nees >= low) & (mean_nees <= high))
    assert inside >= 0.75, f"mean NEES inside the band at {inside:.0%} of steps"
    assert low <= float(np.mean(mean_nees)) <= high


def test_a_turn_across_psi_pi_keeps_the_filter_sound() -> None:
    """Cylinders only, known motion, heading through ±π: the wrap must not jerk anything."""
    landmarks = [(0.0, 5.0), (5.0, 0.0), (-5.0, 0.0), (0.0, -5.0)]
    sensor = Pose2D(0.0, 0.0, 0.0)
    rng = np.random.default_rng(7)
    truth = np.array([0.0, -2.0, math.radians(170.0)])
    ekf = LauncherEkf()
    ekf.reset(Pose2D(*truth), np.diag([1e-4, 1e-4, 1e-5]), t_s=0.0)
    velocity = np.array([0.5, 0.0, math.radians(5.0)])
    cov_v = np.diag([0.01**2, 0.01**2, math.radians(0.2) ** 2])
    worst = 0.0
    for step in range(1, 201):
        t_s = step * 0.05
        truth = compound(
            truth, velocity * 0.05 + rng.multivariate_normal(np.zeros(3), cov_v) * 0.05
        )
        ekf.predict(t_s, BodyMotion(velocity, cov_v))
        for landmark in landmarks:
            z, _ = cylinder_measurement(truth, landmark, sensor)
            if abs(z[1]) < FOV:
                ekf.update_cylinder(z + rng.normal(0, [0.005, 0.002]), R, landmark, sensor)
        error = ekf.state - truth
        error[2] = wrap_angle_rad(float(error[2]))
        worst = max(worst, float(np.hypot(error[0], error[1])))
        assert -math.pi <= ekf.state[2] < math.pi
    start_yaw, end_yaw = math.radians(170.0), float(truth[2])
    assert end_yaw < 0.0 < start_yaw  # it did cross
    assert worst < 0.05


FOV = math.radians(135.0)
R = np.diag([0.005**2, 0.002**2])


def test_board_measurement_sign_convention() -> None:
    """In front of the board (x < 0), r = -x > 0 and a vehicle turned left sees the board
    turned right: α = -ψ."""
    z, _ = board_measurement(np.array([-7.0, 1.0, 0.1]))
    assert z == pytest.approx([7.0, -0.1])
