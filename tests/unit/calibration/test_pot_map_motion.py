"""The pot map's motion samples: each gate on the samples of the turning wheel refuses
what it says, and every candidate is taken or refused once."""

from __future__ import annotations

import numpy as np

from calibration.pot_map_motion import Motion, MotionParams, select_motion

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
