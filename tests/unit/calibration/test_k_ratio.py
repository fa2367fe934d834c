"""The counter-steer ratio k: from the palm tree's arcs and from steady turns."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from calibration.k_ratio import (
    NEAR_STRAIGHT,
    NO_K_IN_RANGE,
    OUTSIDE_MAP,
    SPEED_UNSTEADY,
    TOO_SLOW,
    WHEEL_UNSTEADY,
    KRatioParams,
    SteadyTurn,
    TurnParams,
    centre_curvature_per_m,
    centre_speed_ratio,
    check_k,
    fit_k_from_arcs,
    fit_k_from_palm_tree,
    fit_k_from_turns,
)
from calibration.palm_tree import PalmTreeFit, PalmTreeParams, fit_palm_tree
from calibration.tyre_map import TyreMap
from tests.unit.calibration.vehicle_runs import (
    ANTENNA_FORWARD_M,
    TRUE_K,
    V_CHAR_MPS,
    WHEELBASE_M,
    palm_tree,
    steady_turn,
)

TURNS = TurnParams(wheelbase_m=WHEELBASE_M, characteristic_speed_mps=V_CHAR_MPS)
HALF_TURN = math.pi


@pytest.fixture(scope="module", params=[1, 2])
def palm(request: pytest.FixtureRequest) -> PalmTreeFit:
    samples = palm_tree(seed=request.param).samples()
    params = PalmTreeParams(WHEELBASE_M, ANTENNA_FORWARD_M, 0.0, V_CHAR_MPS)
    return fit_palm_tree(samples, params)


def test_palm_tree_k_is_within_2_percent_of_the_simulator_s(palm: PalmTreeFit) -> None:
    fit = fit_k_from_palm_tree(palm, KRatioParams(linkage_k=0.6))
    assert fit.accepted, fit.reasons
    assert fit.k == pytest.approx(TRUE_K, rel=0.02)
    assert abs(fit.k - TRUE_K) < 4 * fit.k_sigma
    assert fit.rejected == {NEAR_STRAIGHT: sum(abs(a.wheel_rad) < 1 for a in palm.arcs)}


def test_turning_tests_give_k_within_2_percent_and_agree(palm: PalmTreeFit) -> None:
    assert palm.tyre_map is not None
    wheels = (-3 * HALF_TURN, -2 * HALF_TURN, 2 * HALF_TURN, 3 * HALF_TURN)
    turns = [steady_turn(w, 1.5, 15.0, seed=i) for i, w in enumerate(wheels)]
    turning = fit_k_from_turns(turns, palm.tyre_map.tyre_map, TURNS)
    assert turning.accepted, turning.reasons
    assert turning.k == pytest.approx(TRUE_K, rel=0.02)
    assert len(turning.turns) == 4
    check = check_k(fit_k_from_palm_tree(palm), turning)
    assert check.agree, check.reasons


def test_exact_arcs_give_exact_k() -> None:
    front = np.radians([-30.0, -20.0, -10.0, 0.5, 10.0, 20.0, 30.0])
    fit = fit_k_from_arcs(front, 0.6 * front, np.full(7, 1e-3))
    assert fit.k == pytest.approx(0.6, rel=1e-12)
    assert fit.rejected == {NEAR_STRAIGHT: 1}
    assert fit.arcs_used == 6
    assert fit.residual_rms_deg < 1e-9


@given(st.randoms(use_true_random=False), st.integers(0, 2**32 - 1))
def test_k_does_not_depend_on_the_order_of_the_arcs(order: object, seed: int) -> None:
    rng = np.random.default_rng(seed)
    front = rng.uniform(-0.55, 0.55, 9)
    rear = 0.63 * front + rng.normal(0, 0.003, 9)
    sigma = rng.uniform(0.001, 0.004, 9)
    permutation = list(range(9))
    order.shuffle(permutation)  # type: ignore[attr-defined]
    first = fit_k_from_arcs(front, rear, sigma)
    shuffled = fit_k_from_arcs(front[permutation], rear[permutation], sigma[permutation])
    assert shuffled.k == pytest.approx(first.k, rel=1e-12)
    assert shuffled.k_sigma == pytest.approx(first.k_sigma, rel=1e-9)
    assert shuffled.rejected == first.rejected
    assert sorted(shuffled.residuals_rad) == pytest.approx(sorted(first.residuals_rad))


def test_verdicts_name_their_thresholds() -> None:
    front = np.radians([10.0, 20.0, 30.0])
    fit = fit_k_from_arcs(front, 0.5 * front, np.full(3, 0.01), KRatioParams(linkage_k=0.6))
    assert not fit.accepted
    assert any("3 arcs used, at least 4" in r for r in fit.reasons)
    assert any("k sigma" in r for r in fit.reasons)
    assert any("17 % from the linkage's 0.6" in r for r in fit.reasons)
    straight = fit_k_from_arcs([0.0, 0.01], [0.0, 0.006], [0.001, 0.001])
    assert not straight.accepted
    assert math.isnan(straight.k)
    assert straight.rejected == {NEAR_STRAIGHT: 2}


@pytest.mark.parametrize(
    ("front", "rear", "sigma", "message"),
    [
        ([0.1, math.nan], [0.06, 0.1], [0.01, 0.01], "non-finite"),
        ([0.1, 0.2], [0.06], [0.01, 0.01], "differ in length"),
        ([0.1, 0.2], [0.06, 0.1], [0.01, -0.01], "negative"),
        ([], [], [], "at least 1"),
    ],
)
def test_garbage_raises_value_error(
    front: list[float], rear: list[float], sigma: list[float], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        fit_k_from_arcs(front, rear, sigma)


def ideal_turn(wheel: float, k: float, speed: float = 1.5, **changes: np.ndarray) -> SteadyTurn:
    """A turn exactly as the model says, on a linear 1:18 map."""
    t = np.arange(100) * 0.1
    front = wheel / 18.0
    gain = 1.0 / (1.0 + (speed / V_CHAR_MPS) ** 2)
    yaw_rate = centre_curvature_per_m(front, k, WHEELBASE_M, gain) * speed
    columns = {
        "t_s": t,
        "heading_rad": yaw_rate * t,
        "speed_mps": np.full(100, speed),
        "wheel_rad": np.full(100, wheel),
    }
    columns.update(changes)
    return SteadyTurn(**columns)


LINEAR = TyreMap((1 / 18.0,), -9.5, 9.5)


def test_ideal_turns_give_the_exact_k_and_each_rejection_its_reason() -> None:
    t = np.arange(100) * 0.1
    turns = [
        ideal_turn(6.0, 0.63),
        ideal_turn(-9.0, 0.63),
        ideal_turn(0.5, 0.63),  # 1.6 deg of tyre
        ideal_turn(6.0, 0.63, wheel_rad=6.0 + 0.1 * np.sin(t)),
        ideal_turn(6.0, 0.63, speed=0.3),
        ideal_turn(6.0, 0.63, speed_mps=1.5 + 0.5 * np.sin(t)),
        ideal_turn(12.0, 0.63),
        ideal_turn(6.0, 2.5),  # turns harder than any k up to 1.5 allows
    ]
    fit = fit_k_from_turns(turns, LINEAR, TURNS)
    assert fit.k == pytest.approx(0.63, rel=1e-9)
    assert [turn.k for turn in fit.turns] == pytest.approx([0.63, 0.63], rel=1e-9)
    assert fit.rejected == {
        NEAR_STRAIGHT: 1,
        WHEEL_UNSTEADY: 1,
        TOO_SLOW: 1,
        SPEED_UNSTEADY: 1,
        OUTSIDE_MAP: 1,
        NO_K_IN_RANGE: 1,
    }
    assert fit.accepted


def test_check_flags_measurements_that_disagree() -> None:
    front = np.radians([-30.0, -20.0, -10.0, 10.0, 20.0, 30.0])
    palm = fit_k_from_arcs(front, 0.63 * front, np.full(6, 1e-3))
    turning = fit_k_from_turns([ideal_turn(6.0, 0.66), ideal_turn(-6.0, 0.66)], LINEAR, TURNS)
    check = check_k(palm, turning)
    assert not check.agree
    assert check.relative_difference == pytest.approx(0.03 / 0.63, rel=1e-6)
    assert "+4.8 %" in check.reasons[0]


def test_turn_garbage_raises_value_error() -> None:
    with pytest.raises(ValueError, match="at least 10"):
        ideal_turn(6.0, 0.63, t_s=np.arange(5) * 0.1)
    with pytest.raises(ValueError, match="t_s must increase"):
        ideal_turn(6.0, 0.63, t_s=np.zeros(100))
    with pytest.raises(ValueError, match="no steady turns"):
        fit_k_from_turns([], LINEAR, TURNS)
    with pytest.raises(ValueError, match="wheelbase_m"):
        TurnParams(wheelbase_m=-1.0)


@given(
    st.floats(0.5, 3.0),
    st.floats(0.05, 0.5),
    st.floats(-4.0, 4.0),
    st.floats(-1.0, 1.0),
    st.floats(-0.1, 0.1),
    st.booleans(),
)
def test_the_centre_speed_ratio_is_the_rigid_bodys(
    v_centre: float, yaw_rate: float, a: float, lat: float, beta: float, right: bool
) -> None:
    """Against the rigid-body velocity of the antenna point, computed directly."""
    omega = -yaw_rate if right else yaw_rate
    vx, vy = v_centre * math.cos(beta), v_centre * math.sin(beta)
    v_antenna = math.hypot(vx - omega * lat, vy + omega * a)
    if v_centre / abs(omega) < 1.5 * math.hypot(a, lat):
        return  # a turn about a point near the antenna: not a palm tree's or a turn test's
    ratio = centre_speed_ratio(v_antenna, omega, a, lat, beta)
    assert v_antenna * ratio == pytest.approx(v_centre, rel=1e-9)
