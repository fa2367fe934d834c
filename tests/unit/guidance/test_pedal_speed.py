"""Speed by throttle and brake, in closed loop with the simulated Husky.

The plant is ``appliance.sim.vehicle.step`` with the ``husky`` profile: throttle gives a
lagged acceleration of up to 1 m/s² (45 % throttle limit: 0.45 m/s²), the brake up to
3 m/s², drag 0.05 /s. Figures are checked against what that plant allows, worked out
here by hand, and every trace is checked for the pedal rules (never both pedals, each
pedal's rate bounded) on every step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.guidance.pedal_speed import (
    PedalCommand,
    PedalSpeedController,
    PedalSpeedParams,
    PedalState,
)
from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from drivers.pc104.messages import MotionPattern

CONFIG = load_config("husky")
PLANT = VehicleParams.from_config(CONFIG)
PARAMS = PedalSpeedParams.from_limits(CONFIG.limits)
DT_S = 0.02  # the daemon's 50 Hz control rate
TEN_MPH = 4.47
TOL = 1e-9


@dataclass
class Trace:
    t_s: np.ndarray
    target_mps: np.ndarray
    speed_mps: np.ndarray
    odometer_m: np.ndarray
    throttle_pct: np.ndarray
    brake_pct: np.ndarray
    states: list[PedalState]
    integral_mps2: np.ndarray
    end: VehicleState


def drive(
    target_of: Callable[[float], float],
    duration_s: float,
    *,
    params: PedalSpeedParams = PARAMS,
    plant: VehicleParams = PLANT,
    controller: PedalSpeedController | None = None,
    state: VehicleState | None = None,
    t0_s: float = 0.0,
    speed_noise_mps: float = 0.0,
    stop_from_s: float = math.inf,
) -> Trace:
    """Run controller and plant together; the measured speed may carry noise."""
    ctrl = controller if controller is not None else PedalSpeedController(params)
    vehicle = state if state is not None else VehicleState()
    rng = np.random.default_rng(7)
    rows: list[tuple[float, ...]] = []
    states: list[PedalState] = []
    for i in range(round(duration_s / DT_S)):
        t = t0_s + i * DT_S
        measured = vehicle.speed_mps + speed_noise_mps * float(rng.standard_normal())
        cmd = ctrl.update(target_of(t), measured, None, t, stop_requested=t >= stop_from_s)
        speeds = (target_of(t), vehicle.speed_mps, vehicle.odometer_m)
        rows.append((t, *speeds, cmd.throttle_pct, cmd.brake_pct, ctrl.integral_mps2))
        states.append(cmd.state)
        wheels = VehicleCommand(
            pattern=MotionPattern.STRAIGHT, throttle_pct=cmd.throttle_pct, brake_pct=cmd.brake_pct
        )
        vehicle = step(vehicle, wheels, DT_S, plant)
    a = np.array(rows)
    return Trace(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], a[:, 5], states, a[:, 6], vehicle)


def check_pedal_rules(trace: Trace, params: PedalSpeedParams = PARAMS) -> None:
    """Never both pedals; each pedal moves no faster than its rate, on every step."""
    assert not np.any((trace.throttle_pct > 0) & (trace.brake_pct > 0))
    assert np.all(trace.throttle_pct <= params.throttle_max_pct + TOL)
    d_throttle = np.diff(trace.throttle_pct)
    assert d_throttle.max(initial=0) <= params.throttle_rise_pct_per_s * DT_S + TOL
    assert d_throttle.min(initial=0) >= -params.throttle_fall_pct_per_s * DT_S - TOL
    d_brake = np.diff(trace.brake_pct)
    assert d_brake.max(initial=0) <= params.brake_rise_pct_per_s * DT_S + TOL
    releasing = np.array([s is PedalState.RELEASE for s in trace.states[1:]])
    assert np.all(d_brake[~releasing] >= -params.brake_fall_pct_per_s * DT_S - TOL)
    assert np.all(d_brake[releasing] >= -params.hold_release_pct_per_s * DT_S - TOL)
    # Releasing fast is only for a vehicle that stands still.
    assert np.all(np.abs(trace.speed_mps[1:][releasing]) < params.standstill_mps)


def first_time(trace: Trace, mask: np.ndarray) -> float:
    assert mask.any()
    return float(trace.t_s[np.argmax(mask)])


def cruising(at_s: float = 40.0) -> tuple[PedalSpeedController, VehicleState]:
    """A controller and a vehicle settled at 10 mph."""
    ctrl = PedalSpeedController(PARAMS)
    trace = drive(lambda t: TEN_MPH, at_s, controller=ctrl)
    return ctrl, trace.end


# -- figures in closed loop ----------------------------------------------------------------


def test_rise_from_rest_to_ten_mph() -> None:
    trace = drive(lambda t: TEN_MPH, 60.0)
    check_pedal_rules(trace)
    # The plant's best: full allowed throttle from t = 0, no lag: v = a/c·(1 - e^(-c·t)).
    a_max = PARAMS.throttle_max_pct / 100 * PLANT.max_accel_mps2
    drag = PLANT.drag_per_s

    def fastest_s(v: float) -> float:
        return -math.log(1.0 - v * drag / a_max) / drag

    rise_s = first_time(trace, trace.speed_mps >= 0.9 * TEN_MPH) - first_time(
        trace, trace.speed_mps >= 0.1 * TEN_MPH
    )
    reach_98_s = first_time(trace, trace.speed_mps >= 0.98 * TEN_MPH)
    assert fastest_s(0.98 * TEN_MPH) <= reach_98_s <= 1.4 * fastest_s(0.98 * TEN_MPH)
    assert rise_s < 14.0  # 10 -> 90 %: 12.8 s measured, 11.5 s at best
    overshoot = trace.speed_mps.max() - TEN_MPH
    assert overshoot < 0.02  # measured: none
    settled = trace.t_s >= 22.0
    assert np.all(np.abs(trace.speed_mps[settled] - TEN_MPH) < 0.03)
    steady = trace.speed_mps[trace.t_s >= 30.0] - TEN_MPH
    assert math.sqrt(float(np.mean(steady**2))) < 0.01  # measured 0.002 m/s
    assert not np.any(trace.brake_pct > 0)  # speeding up never touches the brake


def test_step_down_brakes_gently_without_undershoot() -> None:
    ctrl, vehicle = cruising()
    trace = drive(lambda t: 2.0, 20.0, controller=ctrl, state=vehicle, t0_s=40.0)
    check_pedal_rules(trace)
    assert trace.brake_pct.max() > 0  # 2.5 m/s down is more than drag alone
    assert 2.0 - trace.speed_mps.min() < 0.03
    assert np.all(np.abs(trace.speed_mps[trace.t_s >= 50.0] - 2.0) < 0.04)
    decel = -np.diff(trace.speed_mps) / DT_S
    assert decel.max() < 1.0  # comfortable: the reference falls at 0.8 m/s²
    # One switch from throttle to brake and one back: no chatter between the pedals.
    pedal = np.sign(trace.throttle_pct) - np.sign(trace.brake_pct)
    used = pedal[pedal != 0]
    assert np.count_nonzero(np.diff(used)) <= 2


def test_small_step_down_coasts_on_drag() -> None:
    """At 10 mph drag alone slows the truck at 0.22 m/s²: half a m/s less is left to it,
    inside the deadband, and the brake stays off."""
    ctrl, vehicle = cruising()
    lower_mps = TEN_MPH - 0.5
    trace = drive(lambda t: lower_mps, 20.0, controller=ctrl, state=vehicle, t0_s=40.0)
    check_pedal_rules(trace)
    assert not np.any(trace.brake_pct > 0)
    assert PedalState.COAST in trace.states
    assert trace.speed_mps.min() > lower_mps - 0.02
    assert np.all(np.abs(trace.speed_mps[trace.t_s >= 52.0] - lower_mps) < 0.02)


def test_smooth_stop_reaches_standstill_and_holds_it() -> None:
    ctrl, vehicle = cruising()
    trace = drive(lambda t: 0.0, 45.0, controller=ctrl, state=vehicle, t0_s=40.0)
    check_pedal_rules(trace)
    still = np.abs(trace.speed_mps) < 1e-6
    stop_s = first_time(trace, still)
    stop_m = float(trace.odometer_m[np.argmax(still)] - trace.odometer_m[0])
    # At least what 0.8 m/s² needs (12.5 m), at most that plus 2 s at full speed.
    assert TEN_MPH**2 / (2 * 0.8) <= stop_m <= TEN_MPH**2 / (2 * 0.8) + 2 * TEN_MPH
    decel = -np.diff(trace.speed_mps) / DT_S
    assert decel.max() < 1.0
    # Then 30 s parked: the odometer does not move, throttle closed, brake held.
    parked = trace.t_s >= stop_s + 5.0
    assert trace.t_s[-1] - (stop_s + 5.0) >= 30.0
    assert np.ptp(trace.odometer_m[parked]) == 0.0
    assert np.all(trace.throttle_pct[parked] == 0.0)
    assert np.all(trace.brake_pct[parked] >= PARAMS.hold_brake_pct)
    assert all(s is PedalState.HOLD for s, p in zip(trace.states, parked, strict=True) if p)


def test_no_integration_at_standstill_so_no_lurch() -> None:
    """A minute held at rest with a noisy speed reading stores nothing: the start after it
    is the same, step for step, as the start after five seconds at rest."""

    def start_after(hold_s: float) -> Trace:
        ctrl = PedalSpeedController(PARAMS)
        held = drive(lambda t: 0.0, hold_s, controller=ctrl, speed_noise_mps=0.015)
        assert np.all(held.integral_mps2 == 0.0)
        assert held.brake_pct[-1] >= PARAMS.hold_brake_pct
        return drive(lambda t: TEN_MPH, 15.0, controller=ctrl, t0_s=hold_s)

    short, long = start_after(5.0), start_after(60.0)
    check_pedal_rules(long)
    assert np.allclose(long.throttle_pct, short.throttle_pct, atol=1e-9)
    assert np.allclose(long.speed_mps, short.speed_mps, atol=1e-9)
    assert long.throttle_pct[:10].max() <= PARAMS.throttle_rise_pct_per_s * 10 * DT_S


@pytest.mark.parametrize(
    ("throttle_max_pct", "engine_mps2", "lowered_mps"),
    [
        (10.0, 1.0, 1.0),  # the throttle limit set low: 0.1 m/s² = drag at 2 m/s at best
        (20.0, 0.7, 2.0),  # and a weaker engine than the model: 0.14 m/s², 2.8 m/s at best
    ],
)
def test_anti_windup_after_an_unreachable_target(
    throttle_max_pct: float, engine_mps2: float, lowered_mps: float
) -> None:
    params = replace(PARAMS, throttle_max_pct=throttle_max_pct)
    plant = replace(PLANT, max_accel_mps2=engine_mps2)
    best_mps = throttle_max_pct / 100 * engine_mps2 / PLANT.drag_per_s
    ctrl = PedalSpeedController(params)
    chase = drive(lambda t: TEN_MPH, 30.0, params=params, plant=plant, controller=ctrl)
    assert chase.speed_mps.max() < best_mps < TEN_MPH  # unreachable indeed
    assert chase.speed_mps[-1] > lowered_mps + 0.1  # and now above the new target
    # Saturated for 30 s, yet the integral did not wind up toward its limit.
    assert abs(ctrl.integral_mps2) < 0.25 * params.integral_limit_mps2
    after = drive(
        lambda t: lowered_mps, 30.0, params=params, plant=plant, controller=ctrl, state=chase.end
    )
    check_pedal_rules(after, params)
    above = after.speed_mps > lowered_mps + 0.1
    assert after.t_s[above].max(initial=0.0) - after.t_s[0] < 5.0  # no long overshoot
    assert after.speed_mps[after.t_s >= after.t_s[0] + 20.0].min() > lowered_mps - 0.1


def test_stop_request_brakes_faster_than_the_comfort_rate() -> None:
    ctrl, vehicle = cruising()
    smooth = drive(lambda t: 0.0, 20.0, controller=PedalSpeedController(PARAMS), state=vehicle)
    trace = drive(lambda t: 0.0, 20.0, controller=ctrl, state=vehicle, t0_s=40.0, stop_from_s=40)
    assert trace.throttle_pct[0] == 0.0  # closed on the first cycle
    assert trace.states[0] is PedalState.STOP_REQUEST
    d_brake = np.diff(trace.brake_pct)
    assert d_brake.max() <= PARAMS.stop_brake_rise_pct_per_s * DT_S + TOL
    assert d_brake.max() > PARAMS.brake_rise_pct_per_s * DT_S  # faster than comfort
    reach_s = first_time(trace, trace.brake_pct >= PARAMS.stop_brake_pct) - 40.0
    assert reach_s <= PARAMS.stop_brake_pct / PARAMS.stop_brake_rise_pct_per_s + DT_S
    assert not np.any((trace.throttle_pct > 0) & (trace.brake_pct > 0))

    def distance(t: Trace) -> float:
        return float(t.odometer_m[-1] - t.odometer_m[0])

    assert trace.speed_mps[-1] == 0.0
    # 2.1 m/s² after 0.35 s: about v²/(2·2.1) + v·0.35 ≈ 6.3 m; the smooth stop takes 17 m.
    assert distance(trace) < 8.0 < distance(smooth)


def test_a_lagging_brake_changes_little() -> None:
    """The Husky's cable-pulled brake lags; the sim may model it (brake_time_constant_s):
    with half a second of lag the step down and the stop still behave."""
    plant = replace(PLANT, brake_time_constant_s=0.5)
    ctrl = PedalSpeedController(PARAMS)
    cruise = drive(lambda t: TEN_MPH, 40.0, controller=ctrl, plant=plant)
    down = drive(lambda t: 2.0, 20.0, controller=ctrl, plant=plant, state=cruise.end, t0_s=40.0)
    check_pedal_rules(down)
    assert down.speed_mps.min() > 2.0 - 0.05
    assert np.all(np.abs(down.speed_mps[down.t_s >= 50.0] - 2.0) < 0.04)
    stop = drive(lambda t: 0.0, 30.0, controller=ctrl, plant=plant, state=down.end, t0_s=60.0)
    check_pedal_rules(stop)
    still = np.abs(stop.speed_mps) < 1e-6
    assert np.all(still[stop.t_s >= 70.0])
    assert stop.states[-1] is PedalState.HOLD


def test_engagement_at_speed_is_bumpless() -> None:
    _, vehicle = cruising(at_s=40.0)
    ctrl = PedalSpeedController(PARAMS)
    ctrl.reset(throttle_pct=22.35)  # the foot's throttle at 10 mph: drag / gain
    trace = drive(lambda t: TEN_MPH, 10.0, controller=ctrl, state=vehicle)
    check_pedal_rules(trace)
    assert np.all(np.abs(trace.speed_mps - TEN_MPH) < 0.02)


# -- input handling and parameters ---------------------------------------------------------


@pytest.mark.parametrize(
    ("target", "speed", "accel"),
    [
        (math.nan, 2.0, None),
        (2.0, math.nan, None),
        (2.0, 2.0, math.nan),
        (math.inf, 2.0, None),
        (2.0, 1e6, None),  # no truck does 1000 km/s: a broken producer
    ],
)
def test_bad_input_brakes_and_never_leaks_nan(
    target: float, speed: float, accel: float | None
) -> None:
    ctrl, vehicle = cruising()
    cmd = ctrl.update(target, speed, accel, 40.0)
    assert cmd.state is PedalState.FAULT
    assert cmd.throttle_pct == 0.0
    assert cmd.brake_pct == pytest.approx(PARAMS.stop_brake_rise_pct_per_s * PARAMS.max_step_dt_s)
    assert all(math.isfinite(x) for x in (cmd.brake_pct, cmd.reference_speed_mps))
    good = ctrl.update(TEN_MPH, vehicle.speed_mps, None, 40.02)
    assert good.state is not PedalState.FAULT


def test_limits_come_from_the_vehicle_config() -> None:
    assert PARAMS.throttle_max_pct == CONFIG.limits.throttle_max_pct == 45.0
    assert PARAMS.throttle_rise_pct_per_s <= CONFIG.limits.max_throttle_rate_pct_per_s
    tight = CONFIG.limits.model_copy(update={"brake_max_pct": 30.0, "throttle_max_pct": 12.0})
    params = PedalSpeedParams.from_limits(tight)
    assert params.brake_max_pct == params.stop_brake_pct == params.hold_brake_pct == 30.0
    assert params.throttle_max_pct == 12.0


@pytest.mark.parametrize(
    "change",
    [
        {"kp_per_s": -0.1},
        {"ki_per_s2": math.nan},
        {"throttle_max_pct": 120.0},
        {"throttle_max_pct": 0.0},
        {"hold_brake_pct": 80.0},  # above the stop brake
        {"brake_off_mps2": 0.2},  # no hysteresis left
        {"throttle_rise_pct_per_s": 0.0},
        {"ref_lead_max_mps": 0.0},  # the reference could never leave the vehicle
    ],
)
def test_bad_parameters_are_refused(change: dict[str, float]) -> None:
    with pytest.raises(ValueError, match=r"\w"):
        replace(PARAMS, **change)


# -- properties over any input -------------------------------------------------------------

_cycle = st.tuples(
    st.floats(-5.0, 60.0),  # target
    st.floats(-3.0, 60.0),  # measured speed
    st.one_of(st.none(), st.floats(-10.0, 10.0)),  # measured acceleration
    st.floats(-0.05, 0.5),  # time step, sometimes backwards or late
    st.booleans() | st.just(False),  # stop requested (mostly not)
)


@settings(max_examples=150, deadline=None)
@given(st.lists(_cycle, min_size=1, max_size=60))
def test_outputs_are_finite_in_range_exclusive_and_rate_limited(
    cycles: list[tuple[float, float, float | None, float, bool]],
) -> None:
    p = PARAMS
    ctrl = PedalSpeedController(p)
    now_s, last_now_s = 100.0, None
    before = PedalCommand(0.0, 0.0, PedalState.COAST, "", 0.0)
    for target, speed, accel, dt_s, stop in cycles:
        now_s += dt_s
        cmd = ctrl.update(target, speed, accel, now_s, stop_requested=stop)
        for value in (cmd.throttle_pct, cmd.brake_pct, cmd.reference_speed_mps):
            assert math.isfinite(value)
        assert 0.0 <= cmd.throttle_pct <= p.throttle_max_pct
        assert 0.0 <= cmd.brake_pct <= p.brake_max_pct
        assert cmd.throttle_pct == 0.0 or cmd.brake_pct == 0.0
        # The reference never runs away from the vehicle (its own kind of windup).
        assert cmd.reference_speed_mps <= max(speed, 0.0) + p.ref_lead_max_mps + TOL
        step_s = 0.0 if last_now_s is None else min(max(now_s - last_now_s, 0.0), p.max_step_dt_s)
        last_now_s = now_s
        d_throttle = cmd.throttle_pct - before.throttle_pct
        d_brake = cmd.brake_pct - before.brake_pct
        assert d_throttle <= p.throttle_rise_pct_per_s * step_s + TOL
        if not stop:
            assert d_throttle >= -p.throttle_fall_pct_per_s * step_s - TOL
            assert d_brake <= p.brake_rise_pct_per_s * step_s + TOL
        else:
            assert cmd.throttle_pct == 0.0
            assert d_brake <= p.stop_brake_rise_pct_per_s * step_s + TOL
        fall = (
            p.hold_release_pct_per_s if cmd.state is PedalState.RELEASE else p.brake_fall_pct_per_s
        )
        assert d_brake >= -fall * step_s - TOL
        if stop or speed <= -p.standstill_mps or target < p.standstill_mps:
            assert cmd.throttle_pct <= before.throttle_pct  # never opens toward a stop
        before = cmd
