"""Per-rule safety tests, then one generic property suite over every rule.

In the spirit of opendbc's ``safety/tests/common.py``: each rule has its own class of
targeted tests, and the property suite runs every rule over random inputs and random
limits drawn from valid config values, checking the invariants no rule may break.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import parts
from appliance.config.models import Limits, Staleness
from safety.arbitration import RELEASED, OperatorInput, arbitrate, safe_command
from safety.limits import ActuatorCommand, CommandLimiter, LimitParams
from safety.staleness import DEFAULT_CRITICAL_INPUTS, StalenessGuard

DEG = math.pi / 180.0
PARAMS = parts.limit_params(Limits())  # 30 deg, 20 deg/s, throttle 0..40 at 50 %/s
DT = 0.02


def limiter_at(angle_rad: float = 0.0, now_s: float = 0.0) -> CommandLimiter:
    """A limiter whose steering reference is ``angle_rad`` at ``now_s``."""
    limiter = CommandLimiter(PARAMS)
    limiter.update(ActuatorCommand(angle_rad, 0.0, 0.0), 0.0, now_s, angle_rad)
    return limiter


class TestAbsoluteLimits:
    def test_conversion_to_radians_happens_at_the_edge(self) -> None:
        assert PARAMS.max_steer_angle_rad == pytest.approx(30 * DEG)
        assert PARAMS.max_steer_rate_rad_per_s == pytest.approx(20 * DEG)

    def test_steer_angle_clamped_both_ways(self) -> None:
        for sign in (1.0, -1.0):
            limiter = limiter_at(sign * 29.9 * DEG)
            out, violations = limiter.update(ActuatorCommand(sign * 1.0, 0.0, 0.0), 0.0, 1.0)
            assert out.steer_angle_rad == pytest.approx(sign * 30 * DEG)
            assert "steer_angle_above_max" in violations

    def test_throttle_max_and_negative(self) -> None:
        limiter = CommandLimiter(PARAMS)
        for t in range(1, 200):
            out, _ = limiter.update(ActuatorCommand(None, 100.0, 0.0), 0.0, t * DT)
        assert out.throttle_pct == pytest.approx(40.0)
        out, violations = limiter.update(ActuatorCommand(None, -5.0, 0.0), 0.0, 10.0)
        assert (out.throttle_pct, violations) == (0.0, ("throttle_below_zero",))

    def test_brake_range(self) -> None:
        params = parts.limit_params(Limits(brake_min_pct=5.0, brake_max_pct=80.0))
        limiter = CommandLimiter(params)
        assert limiter.update(ActuatorCommand(None, 0, 99.0), 0, 0)[0].brake_pct == 80.0
        out, violations = limiter.update(ActuatorCommand(None, 0, 0.0), 0, DT)
        assert (out.brake_pct, violations) == (5.0, ("brake_below_min",))

    def test_within_limits_passes_unchanged(self) -> None:
        limiter = limiter_at(0.1)
        command = ActuatorCommand(0.1 + 0.001, 0.0, 20.0)
        assert limiter.update(command, 1.0, DT) == (command, ())


class TestRateLimits:
    def test_steer_rate_against_previous_output(self) -> None:
        limiter = limiter_at(0.0)
        out, violations = limiter.update(ActuatorCommand(0.5, 0, 0), 0.0, DT)
        assert out.steer_angle_rad == pytest.approx(20 * DEG * DT)
        assert violations == ("steer_rate_above_max",)

    def test_first_angle_after_reset_starts_from_the_measured_angle(self) -> None:
        limiter = CommandLimiter(PARAMS)
        out, violations = limiter.update(ActuatorCommand(0.0, 0, 0), 0.0, 5.0, 0.3)
        assert out.steer_angle_rad == pytest.approx(0.3)  # no dt yet: held where it is
        assert violations == ("steer_rate_above_max",)

    def test_no_measured_angle_keeps_steering_released(self) -> None:
        out, violations = CommandLimiter(PARAMS).update(ActuatorCommand(0.1, 0, 0), 0.0, 0.0)
        assert out.steer_angle_rad is None
        assert violations == ("steer_no_reference",)

    def test_speed_dependent_steer_rate(self) -> None:
        params = parts.limit_params(Limits(), steer_rate_fraction_at_max_speed=0.5)
        assert params.steer_rate_limit_rad_per_s(0.0) == pytest.approx(20 * DEG)
        assert params.steer_rate_limit_rad_per_s(-100.0) == pytest.approx(10 * DEG)

    def test_a_gap_in_updates_is_not_a_licence_for_a_big_step(self) -> None:
        limiter = limiter_at(0.0)
        out, _ = limiter.update(ActuatorCommand(0.5, 0, 0), 0.0, 100.0)
        assert out.steer_angle_rad == pytest.approx(20 * DEG * PARAMS.max_step_dt_s)

    def test_time_going_backwards_allows_no_change(self) -> None:
        limiter = limiter_at(0.0, now_s=10.0)
        assert limiter.update(ActuatorCommand(0.5, 0, 0), 0.0, 9.0)[0].steer_angle_rad == 0.0

    def test_throttle_rises_at_rate_and_falls_at_once(self) -> None:
        limiter = CommandLimiter(PARAMS)
        limiter.update(ActuatorCommand(None, 0, 0), 0, 0.0)
        out, violations = limiter.update(ActuatorCommand(None, 30.0, 0), 0, DT)
        assert out.throttle_pct == pytest.approx(50.0 * DT)
        assert violations == ("throttle_rate_above_max",)
        assert limiter.update(ActuatorCommand(None, 0.0, 0), 0, 2 * DT) == (
            ActuatorCommand(None, 0.0, 0.0),
            (),
        )

    def test_throttle_minimum_is_reached_at_once_and_below_it_closes(self) -> None:
        limiter = CommandLimiter(parts.limit_params(Limits(throttle_min_pct=10.0)))
        limiter.update(ActuatorCommand(None, 0, 0), 0, 0.0)
        assert limiter.update(ActuatorCommand(None, 30.0, 0), 0, DT)[0].throttle_pct == 11.0
        assert limiter.update(ActuatorCommand(None, 5.0, 0), 0, 2 * DT)[0].throttle_pct == 0.0


class TestNonFinite:
    @pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
    @pytest.mark.parametrize("field", ["steer", "throttle", "brake", "speed", "now", "measured"])
    def test_non_finite_anywhere_gives_the_safe_command(self, bad: float, field: str) -> None:
        limiter = limiter_at(0.1)
        command = ActuatorCommand(
            bad if field == "steer" else 0.1,
            bad if field == "throttle" else 10.0,
            bad if field == "brake" else 0.0,
        )
        out, violations = limiter.update(
            command,
            bad if field == "speed" else 1.0,
            bad if field == "now" else DT,
            bad if field == "measured" else 0.1,
        )
        assert out == PARAMS.safe_command()
        assert violations == ("input_not_finite",)

    def test_after_a_safe_command_steering_needs_a_new_reference(self) -> None:
        limiter = limiter_at(0.1)
        limiter.update(ActuatorCommand(math.nan, 0, 0), 0, DT)
        assert limiter.update(ActuatorCommand(0.1, 0, 0), 0, 2 * DT)[0].steer_angle_rad is None


FRESH = {name: 0.0 for name in parts.age_limits(Staleness())}


class TestStaleness:
    GUARD = parts.staleness_guard(Staleness())

    def test_all_fresh_is_quiet(self) -> None:
        assert self.GUARD.update(FRESH, 0.0) == ()

    def test_age_at_the_limit_is_fresh_beyond_it_stale(self) -> None:
        assert self.GUARD.update({**FRESH, "steering.pot": 0.05}, 0.0) == ()
        assert self.GUARD.update({**FRESH, "steering.pot": 0.051}, 0.0) == ("steering.pot",)

    @pytest.mark.parametrize("age", [math.inf, math.nan, -0.01])
    def test_unusable_ages_are_stale(self, age: float) -> None:
        assert self.GUARD.update({**FRESH, "board.brake": age}, 0.0) == ("board.brake",)

    def test_missing_inputs_are_stale(self) -> None:
        assert self.GUARD.update({}, 0.0) == DEFAULT_CRITICAL_INPUTS

    def test_non_critical_inputs_are_not_reported(self) -> None:
        assert "pose" not in DEFAULT_CRITICAL_INPUTS
        assert self.GUARD.update({**FRESH, "pose": 99.0}, 0.0) == ()

    def test_critical_input_without_limit_is_refused_at_construction(self) -> None:
        with pytest.raises(ValueError, match="without an age limit"):
            StalenessGuard({"scan.left": 0.1}, ["scan.left", "lidar.top"])

    def test_remembers_since_when_and_forgets_on_recovery(self) -> None:
        guard = StalenessGuard({"a": 0.1}, ["a"])
        guard.update({}, 1.0)
        guard.update({}, 2.0)
        assert guard.stale_since_s == {"a": 1.0}
        guard.update({"a": 0.0}, 3.0)
        assert guard.stale_since_s == {}


AUTOPILOT = ActuatorCommand(0.2, 15.0, 5.0)


class TestArbitration:
    @pytest.mark.parametrize("steering", [False, True])
    @pytest.mark.parametrize("speed", [False, True])
    @pytest.mark.parametrize("revoked", [False, True])
    @pytest.mark.parametrize(
        "operator",
        [
            OperatorInput(),
            OperatorInput(steering_override=True),
            OperatorInput(brake_pedal=True),
            OperatorInput(throttle_pedal=True),
        ],
    )
    def test_truth_table(
        self, operator: OperatorInput, revoked: bool, speed: bool, steering: bool
    ) -> None:
        out = arbitrate(operator, revoked, AUTOPILOT, steering, speed)
        if revoked and operator.overriding:
            expected = RELEASED
        elif revoked:
            expected = safe_command()
        else:
            steer_ours = steering and not operator.steering_override
            speed_ours = speed and not (operator.brake_pedal or operator.throttle_pedal)
            expected = ActuatorCommand(
                0.2 if steer_ours else None, 15.0 if speed_ours else 0.0, 5.0 if speed_ours else 0.0
            )
        assert out == expected

    def test_no_autopilot_command_releases(self) -> None:
        assert arbitrate(OperatorInput(), False, None, True, True) == RELEASED


# --- Generic property suite: every rule, random inputs, random valid limits ----------

any_float = st.floats(allow_nan=True, allow_infinity=True)
finite = st.floats(-1e6, 1e6)
mostly_finite = st.one_of(finite, finite, finite, any_float)


@st.composite
def ordered_pct_range(draw: st.DrawFn) -> tuple[float, float]:
    """``low < high`` within 0..100 %, by construction: ``high`` is drawn above ``low``."""
    low = draw(st.floats(0.0, 100.0, exclude_max=True))
    return low, draw(st.floats(low, 100.0, exclude_min=True))


@st.composite
def valid_limits(draw: st.DrawFn) -> Limits:
    """Any Limits the config would accept: the rules must hold for all of them.

    Drawn so that the config's validators hold by design (each minimum below its
    maximum, the engage speed within the speed limit): nothing is drawn to be thrown away.
    """
    max_speed = draw(st.floats(0.0, 20.0, exclude_min=True))
    throttle_min, throttle_max = draw(ordered_pct_range())
    brake_min, brake_max = draw(ordered_pct_range())
    return Limits(
        max_steer_angle_deg=draw(st.floats(0.0, 60.0, exclude_min=True)),
        max_steer_rate_deg_per_s=draw(st.floats(0.0, 180.0, exclude_min=True)),
        max_speed_mps=max_speed,
        max_engage_speed_mps=draw(st.floats(0.0, max_speed, exclude_min=True)),
        throttle_min_pct=throttle_min,
        throttle_max_pct=throttle_max,
        max_throttle_rate_pct_per_s=draw(st.floats(0.0, 1000.0, exclude_min=True)),
        brake_min_pct=brake_min,
        brake_max_pct=brake_max,
    )


@st.composite
def valid_params(draw: st.DrawFn) -> LimitParams:
    return parts.limit_params(
        draw(valid_limits()),
        steer_rate_fraction_at_max_speed=draw(st.floats(0.01, 1.0)),
        max_step_dt_s=draw(st.floats(0.001, 1.0)),
    )


commands = st.builds(ActuatorCommand, st.none() | mostly_finite, mostly_finite, mostly_finite)
cycles = st.tuples(commands, mostly_finite, mostly_finite, st.none() | mostly_finite)
operators = st.builds(OperatorInput, st.booleans(), st.booleans(), st.booleans())
EPS = 1e-9


def assert_within_limits(out: ActuatorCommand, p: LimitParams) -> None:
    if out.steer_angle_rad is not None:
        assert abs(out.steer_angle_rad) <= p.max_steer_angle_rad + EPS
    assert out.throttle_pct == 0.0 or p.throttle_min_pct < out.throttle_pct <= p.throttle_max_pct
    assert p.brake_min_pct <= out.brake_pct <= p.brake_max_pct


class TestPropertiesOverAllRules:
    @settings(max_examples=300, deadline=None)
    @given(valid_params(), st.lists(cycles, min_size=1, max_size=30), st.floats(-1e6, 1e6))
    def test_limiter_output_within_limits_and_rates(
        self,
        p: LimitParams,
        sequence: list[tuple[ActuatorCommand, float, float, float | None]],
        start_s: float,
    ) -> None:
        limiter = CommandLimiter(p)
        previous: ActuatorCommand | None = None
        last_now_s: float | None = None
        for command, speed, now_offset, measured in sequence:
            now_s = start_s + now_offset if math.isfinite(now_offset) else now_offset
            out, violations = limiter.update(command, speed, now_s, measured)
            inputs = (command.steer_angle_rad, command.throttle_pct, command.brake_pct)
            non_finite = not all(
                x is None or math.isfinite(x) for x in (*inputs, speed, now_s, measured)
            )
            if non_finite:
                assert (out, violations) == (p.safe_command(), ("input_not_finite",))
                previous, last_now_s = None, None
                continue
            assert_within_limits(out, p)
            dt = 0.0 if last_now_s is None else min(max(now_s - last_now_s, 0.0), p.max_step_dt_s)
            before = None if previous is None else previous.steer_angle_rad
            if before is not None and out.steer_angle_rad is not None:
                step = abs(out.steer_angle_rad - before)
                assert step <= p.steer_rate_limit_rad_per_s(speed) * dt + 1e-6
            prior_throttle = 0.0 if previous is None else previous.throttle_pct
            ramp_from = max(prior_throttle, p.throttle_min_pct)
            assert out.throttle_pct <= ramp_from + p.max_throttle_rate_pct_per_s * dt + 1e-6
            previous, last_now_s = out, now_s

    @settings(max_examples=300, deadline=None)
    @given(
        st.dictionaries(st.sampled_from(sorted(FRESH)), any_float),
        st.lists(st.sampled_from(sorted(FRESH)), unique=True),
        st.floats(0.001, 2.0),
    )
    def test_every_stale_critical_input_is_reported(
        self, ages_s: dict[str, float], critical: list[str], limit_s: float
    ) -> None:
        guard = StalenessGuard(dict.fromkeys(FRESH, limit_s), critical)
        stale = guard.update(ages_s, 0.0)
        for name in critical:
            age = ages_s.get(name)
            fresh = age is not None and math.isfinite(age) and 0.0 <= age <= limit_s
            assert (name in stale) is not fresh
        assert set(stale) <= set(critical)

    @given(operators, st.booleans(), st.none() | commands, st.booleans(), st.booleans())
    def test_arbitration_allow_list(
        self,
        operator: OperatorInput,
        revoked: bool,
        autopilot: ActuatorCommand | None,
        steering: bool,
        speed: bool,
    ) -> None:
        out = arbitrate(operator, revoked, autopilot, steering, speed)
        assert out is not None
        if operator.steering_override:
            assert out.steer_angle_rad is None  # the wheel is the operator's
        if operator.brake_pedal or operator.throttle_pedal:
            assert out.throttle_pct == 0.0  # the pedals are the operator's
        if revoked and operator.overriding:
            assert out == RELEASED  # operator > safety: no actuation against them at all
        if revoked or autopilot is None:
            assert out.steer_angle_rad is None
            assert out.throttle_pct == 0.0
        if not steering:
            assert out.steer_angle_rad is None
        if not speed:
            assert out.throttle_pct == 0.0

    @settings(max_examples=200, deadline=None)
    @given(valid_params(), operators, st.booleans(), commands, st.booleans(), st.booleans())
    def test_arbitrated_then_limited_is_within_limits(
        self,
        p: LimitParams,
        operator: OperatorInput,
        revoked: bool,
        autopilot: ActuatorCommand,
        steering: bool,
        speed: bool,
    ) -> None:
        chosen = arbitrate(operator, revoked, autopilot, steering, speed)
        assert chosen is not None
        out, _ = CommandLimiter(p).update(chosen, 0.0, 0.0, 0.0)
        if out != p.safe_command():
            assert_within_limits(out, p)
        if operator.steering_override or revoked:
            assert out.steer_angle_rad is None
        if operator.brake_pedal or operator.throttle_pedal or revoked:
            assert out.throttle_pct == 0.0
