"""The pot map from the turning wheel as well as the rests: the sweep by hand reaches a
tenth of a degree, and each gate on the motion samples refuses what it says."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.pot_map import PotMapParams, PotMapResult, fit_pot_map
from calibration.pot_map_motion import Motion, MotionParams, select_motion
from drivers.actuators.steering_model import PotMapping, ServoParams
from tests.unit.calibration.synthetic import (
    MAPPING,
    SERVO,
    PotSweep,
    hand_sweep,
    map_error_tyre_deg,
    pot_sweep,
)

TARGET_TYRE_DEG = 0.1  # the map's 0.2° figure with margin, so the runtime test holds
RATIO = SERVO.steering_ratio
RESTS_ONLY = PotMapParams(motion=MotionParams(takeup_rad=math.inf))


def fit(
    sweep: PotSweep,
    centre: float | None = MAPPING.centre_counts,
    params: PotMapParams | None = None,
) -> PotMapResult:
    columns = (sweep.t_s, sweep.encoder_wheel_rad, sweep.pot_counts, sweep.commanded_wheel_rad)
    return fit_pot_map(*columns, RATIO, centre, params)


@pytest.mark.parametrize("seed", range(6))
def test_a_sweep_by_hand_reaches_a_tenth_of_a_degree(seed: int) -> None:
    result = fit(hand_sweep(seed, glitches=12))
    assert result.verdict.accepted, result.verdict.reasons
    assert map_error_tyre_deg(result) < TARGET_TYRE_DEG
    assert result.motion_samples > 300
    assert result.powers == tuple(range(1, 10))  # the motion samples fill the sweep
    assert result.residual_max_tyre_deg < TARGET_TYRE_DEG


def test_without_the_motion_samples_the_rests_miss_between_them() -> None:
    """The problem this solves: the half-turn rests alone pin only three distances from
    the centre, and an odd polynomial through them misses the truth in between."""
    sweep = hand_sweep(0)
    rests_only, both = fit(sweep, params=RESTS_ONLY), fit(sweep)
    assert rests_only.motion_samples == 0 and rests_only.powers == (1, 3, 5)
    assert map_error_tyre_deg(rests_only) > TARGET_TYRE_DEG
    assert map_error_tyre_deg(both) < map_error_tyre_deg(rests_only) / 4


def test_by_hand_the_encoder_trails_the_wheel() -> None:
    """Hands drag the released servo: the gap between the directions comes out negative.
    Its size is the play less what the hand's tremor at the rests takes up."""
    result = fit(hand_sweep(1, servo=ServoParams(backlash_rad=0.1)))
    assert result.backlash_rad == pytest.approx(-0.1, abs=0.01)
    assert fit(pot_sweep(1)).backlash_rad == pytest.approx(SERVO.backlash_rad, abs=0.005)


def test_a_centre_a_few_counts_off_only_moves_the_zero() -> None:
    """With every power allowed the map's shape does not depend on the centre: 3 counts
    off shift it by their own 0.05°, and it bends no further."""
    result = fit(hand_sweep(2), MAPPING.centre_counts + 3.0)
    assert result.verdict.accepted, result.verdict.reasons
    assert map_error_tyre_deg(result, relative=True) < TARGET_TYRE_DEG / 4


def test_a_fast_hand_leaves_the_rests_and_the_slow_ends() -> None:
    result = fit(hand_sweep(3, pace_rad_per_s=(6.0, 9.0)))
    assert result.verdict.accepted, result.verdict.reasons
    assert result.rejected["too_fast"] > result.motion_samples > 0
    assert map_error_tyre_deg(result) < TARGET_TYRE_DEG


def test_by_hand_a_rest_after_a_railed_lock_keeps_its_direction() -> None:
    """A pot that rails at the locks leaves no rest there: the first rest after one
    still came from the lock, whatever the rest before it was."""
    gain = 280.0  # past the ADC's range at both locks
    mapping = PotMapping(gain_counts_per_rad=gain, cubic_counts_per_rad3=-0.35 * gain / 180.0)
    sweep = hand_sweep(0, mapping=mapping)
    result = fit(sweep, mapping.centre_counts)
    assert result.verdict.accepted, result.verdict.reasons
    bottom = sweep.t_s[np.argmin(sweep.encoder_wheel_rad[: sweep.t_s.size // 2])]
    top = sweep.t_s[np.argmax(sweep.encoder_wheel_rad)]
    for rest in result.pauses:
        if rest.start_t_s > bottom:
            assert rest.direction == (1 if rest.start_t_s < top else -1), rest


@pytest.mark.parametrize("seed", range(4))
def test_a_servo_sweep_adds_its_slowing_approaches(seed: int) -> None:
    """Commanded half turns: the servo slews at 6 rad/s (too fast to use) and slows into
    each rest, those samples join the rests; no gap is filled, so odd powers only."""
    result = fit(pot_sweep(seed, glitches=12))
    assert result.verdict.accepted, result.verdict.reasons
    assert result.motion_samples > 0 and result.rejected["too_fast"] > 0
    assert all(k % 2 for k in result.powers)
    assert map_error_tyre_deg(result) < TARGET_TYRE_DEG


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    backlash_rad=st.floats(0.02, 0.14),  # with none, a tremor leaves no rest still
    slowest=st.floats(0.5, 4.0),
    tremor_rad=st.floats(0.0, 0.003),
    glitches=st.integers(0, 30),
    encoder_zero_rad=st.floats(-3.0, 3.0),
)
def test_sweeps_by_hand_count_every_sample_once_and_hold_the_target(
    seed: int,
    backlash_rad: float,
    slowest: float,
    tremor_rad: float,
    glitches: int,
    encoder_zero_rad: float,
) -> None:
    sweep = hand_sweep(
        seed,
        servo=ServoParams(backlash_rad=backlash_rad),
        pace_rad_per_s=(slowest, 2.0 * slowest),
        tremor_rad=tremor_rad,
        glitches=glitches,
        encoder_zero_rad=encoder_zero_rad,
    )
    result = fit(sweep)
    assert result.accepted + sum(result.rejected.values()) == result.samples == sweep.t_s.size
    assert result.verdict.accepted, result.verdict.reasons
    assert result.monotonic
    assert map_error_tyre_deg(result) < TARGET_TYRE_DEG


# --- The gates, on a recording made to order. ---

HZ = 50.0


def stroke(t0: float, start: float, stop: float, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """The encoder turning from ``start`` to ``stop`` at ``rate`` rad/s, sampled at 50 Hz."""
    n = round(abs(stop - start) / rate * HZ)
    return t0 + np.arange(n) / HZ, start + (stop - start) * np.arange(n) / n


def gates(
    encoder: np.ndarray, pot: np.ndarray, pot_range: tuple[float, float] = (0.0, 4095.0)
) -> Motion:
    t = np.arange(encoder.size) / HZ
    candidate = np.ones(encoder.size, np.bool_)
    return select_motion(t, encoder, pot, candidate, pot_range, MotionParams())


def test_each_candidate_is_taken_or_refused_under_one_gate() -> None:
    _, up = stroke(0.0, 0.0, 2.0, 1.0)
    _, down = stroke(0.0, 2.0, -1.0, 1.0)
    encoder = np.concatenate([up, down])
    pot = 2000.0 + 180.0 * encoder
    pot[20] += 40.0  # a glitch mid-stroke (a bigger one would be past the range too)
    motion = gates(encoder, pot, (1900.0, 2300.0))
    refused = motion.refused
    total = motion.index.size + sum(int(np.count_nonzero(m)) for m in refused.values())
    assert total == encoder.size
    assert refused["no_direction"][0] and not refused["no_direction"][2:].any()
    assert np.flatnonzero(refused["pot_glitch"]).tolist() == [20]
    # The play is taken up 0.15 rad after the start and after the turn back at 2 rad.
    in_play = np.flatnonzero(refused["in_play"])
    assert np.all((encoder[in_play] < 0.15) | (encoder[in_play] > 2.0 - 0.15))
    assert np.all(motion.direction[encoder[motion.index] > 1.9] == 1.0)
    assert refused["past_travel"].any()  # up to 2 rad the pot reads beyond 2300
    assert np.all(pot[motion.index] <= 2300.0)


def test_thinning_keeps_one_sample_per_spacing_of_each_stroke() -> None:
    _, encoder = stroke(0.0, 0.0, 3.0, 0.5)
    motion = gates(encoder, 2000.0 + 180.0 * encoder)
    taken = encoder[motion.index]
    assert np.all(np.diff(taken) >= MotionParams().spacing_rad - 1e-9)
    assert motion.refused["thinned"].sum() > taken.size  # 0.01 rad a sample at 0.5 rad/s


def test_a_fast_stretch_is_refused_and_the_slow_one_kept() -> None:
    _, slow = stroke(0.0, 0.0, 2.0, 1.0)
    _, fast = stroke(0.0, 2.0, 6.0, 5.0)
    encoder = np.concatenate([slow, fast])
    motion = gates(encoder, 2000.0 + 180.0 * encoder)
    too_fast = np.flatnonzero(motion.refused["too_fast"])
    assert too_fast.size > 0 and np.all(encoder[too_fast] > 1.9)
    assert np.all(encoder[motion.index] < 2.1)
