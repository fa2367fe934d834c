"""The pot-map sweep's motion samples: the wheel turning steadily between the rests.

Half turns on a wheel with ±9.4 rad of travel give some seven rests each way, at three
distances from the centre: a polynomial through so few positions stays of low degree
and still swings between them (on the simulated vehicle, turned by hand, the rests alone
missed the truth by 0.12° of tyre angle between them; the goal is 0.1°). The samples
taken while the wheel turns fill those gaps. The pot and the encoder are read in the
same telemetry frame, so a turning wheel does not put one behind the other; and once
the coupling's play is taken up, a sample obeys the rests' own model, ``encoder =
offset + f(pot) + direction * backlash / 2`` (:mod:`calibration.pot_map_branches`). The
rests stay: they are the paper's method, and, each averaged over a second or two, they
pin the backlash and the map where single samples are noisiest.

A sample outside the rests (:mod:`calibration.pot_map_pauses`) is used if it passes
these gates, and refused under the first it fails:

- ``no_direction``: the encoder has not yet moved more than ``back_tol_rad`` one way;
- ``in_play``: since the encoder last turned back (more than ``back_tol_rad`` from its
  furthest point), it has come less than ``takeup_rad``, the most backlash the fit
  accepts, so the play may not be taken up yet;
- ``too_fast``: the encoder's pace over ``rate_window_s`` is above
  ``max_rate_rad_per_s``, past which a millisecond between the pot's ADC conversion and
  the encoder's latch in one frame would cost more than 0.01° of tyre angle;
- ``past_travel``: the pot lies outside the rests used (past a lock, or past the pot's
  own travel), where nothing pins the map;
- ``pot_glitch``: the pot is more than ``pot_glitch_counts`` from the median of its
  ``glitch_window`` neighbours each side (while the wheel turns one way the readings are
  monotonic, so the median is the sample itself less its noise);
- ``thinned``: within ``spacing_rad`` of encoder travel of the last sample taken in the
  same stroke, so that a slow stretch does not weigh more than a fast one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.fit_checks import BoolArray, FloatArray, IntArray


@dataclass(frozen=True)
class MotionParams:
    back_tol_rad: float = 0.002  # two encoder ticks: noise, not a turn back
    takeup_rad: float = 0.15  # PotMapParams.max_backlash_rad: more play is refused anyway
    max_rate_rad_per_s: float = 3.0  # 1 ms of skew at 3 rad/s: 0.003 rad, 0.01° of tyre
    rate_window_s: float = 0.2
    glitch_window: int = 2
    pot_glitch_counts: float = 5.0  # as for the rests: six times the pot's noise
    spacing_rad: float = 0.05


@dataclass(frozen=True)
class Motion:
    index: IntArray  # the samples taken, in time order
    direction: FloatArray  # +1: the encoder moving up, -1: down
    refused: dict[str, BoolArray]  # per reason, each candidate refused under one


def select_motion(
    t: FloatArray,
    encoder: FloatArray,
    pot: FloatArray,
    candidate: BoolArray,
    pot_range: tuple[float, float] | None,
    p: MotionParams,
) -> Motion:
    """The motion samples among ``candidate`` (samples in no rest, the pot not at a
    rail), for a time-ordered recording; ``pot_range``: the rests' used pot readings."""
    direction, travel = _strokes(encoder, p.back_tol_rad)
    low, high = pot_range if pot_range is not None else (np.inf, -np.inf)
    gates = {
        "no_direction": direction == 0,
        "in_play": travel < p.takeup_rad,
        "too_fast": _pace(t, encoder, p.rate_window_s) > p.max_rate_rad_per_s,
        "past_travel": (pot < low) | (pot > high),
        "pot_glitch": np.abs(pot - _running_median(pot, p.glitch_window)) > p.pot_glitch_counts,
    }
    refused: dict[str, BoolArray] = {}
    left = candidate.copy()
    for name, fails in gates.items():
        refused[name] = left & fails
        left &= ~fails
    taken = _thin(encoder, direction, left, p.spacing_rad)
    refused["thinned"] = left & ~taken
    index = np.flatnonzero(taken)
    return Motion(index, direction[index].astype(np.float64), refused)


def _strokes(encoder: FloatArray, back_tol: float) -> tuple[IntArray, FloatArray]:
    """Per sample: the direction of the stroke it is in (0 before the first), and how far
    the encoder has come since that stroke began (where it last turned back)."""
    n = encoder.size
    direction = np.zeros(n, dtype=np.intp)
    travel = np.zeros(n, dtype=np.float64)
    low = high = float(encoder[0])
    d, start, furthest = 0, 0.0, 0.0
    for i, value in enumerate(encoder.tolist()):
        if d == 0:
            low, high = min(low, value), max(high, value)
            if value - low > back_tol:
                d, start, furthest = 1, low, value
            elif high - value > back_tol:
                d, start, furthest = -1, high, value
        elif (value - furthest) * d > 0.0:
            furthest = value
        elif (furthest - value) * d > back_tol:
            d, start, furthest = -d, furthest, value
        direction[i] = d
        travel[i] = (value - start) * d if d else 0.0
    return direction, travel


def _pace(t: FloatArray, encoder: FloatArray, window_s: float) -> FloatArray:
    """The encoder's speed over ``window_s`` centred on each sample (rad/s)."""
    before = np.searchsorted(t, t - window_s / 2.0, side="left")
    after = np.searchsorted(t, t + window_s / 2.0, side="right") - 1
    span = t[after] - t[before]
    with np.errstate(divide="ignore", invalid="ignore"):
        pace = np.abs(encoder[after] - encoder[before]) / span
    return np.where(span > 0.0, pace, 0.0)


def _running_median(values: FloatArray, half_width: int) -> FloatArray:
    """The median of each sample and ``half_width`` neighbours each side (fewer at the ends)."""
    padded = np.pad(values, half_width, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half_width + 1)
    return np.asarray(np.median(windows, axis=1), dtype=np.float64)


def _thin(encoder: FloatArray, direction: IntArray, passed: BoolArray, spacing: float) -> BoolArray:
    """One passed sample per ``spacing`` of encoder travel within each stroke."""
    taken = np.zeros(encoder.size, dtype=np.bool_)
    last_direction, last_taken = 0, 0.0
    for i in np.flatnonzero(passed).tolist():
        d = int(direction[i])
        if d != last_direction or (encoder[i] - last_taken) * d >= spacing:
            taken[i] = True
            last_direction, last_taken = d, float(encoder[i])
    return taken


def judged_residuals(
    residuals: FloatArray,
    encoder: FloatArray,
    direction: FloatArray,
    rest: BoolArray,
    group: int,
) -> FloatArray:
    """The residuals to judge a fit by: each rest's, and the motion samples' means over
    runs of at least ``group`` neighbours of one direction (a single sample's residual
    is the pot's noise, up to 0.05° of tyre near a lock; a run's mean is the map's)."""
    judged = [residuals[rest]]
    for way in (-1.0, 1.0):
        chosen = np.flatnonzero(~rest & (direction == way))
        if chosen.size < group:  # too few to tell the map from the noise: the rests judge
            continue
        runs = chosen[np.argsort(encoder[chosen], kind="stable")]
        judged.extend(
            np.array([residuals[run].mean()]) for run in np.array_split(runs, runs.size // group)
        )
    return np.concatenate(judged)
