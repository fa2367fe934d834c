"""The pot-map maneuver's pauses: where the wheel stood still, and from which side it came.

Stanley et al.'s second step (Fig. 17): the vehicle stands, the wheel is turned from full
right to full left and back in half turns, pausing after each, and the servo's encoder
and the pot are recorded. The pauses (the rests) are the paper's points: each averages
a second or more of still readings, so they pin the backlash and the map where single
samples are noisiest. The samples between them, the wheel turning, are judged by
:mod:`calibration.pot_map_motion`; the reasons below for refusing a sample as part of a
rest (``moving``, ``short_pause``, ``no_direction``, ``in_play``) hand it on to that
module, which uses it or refuses it under its own gates.

A pause is a stretch of constant command (a *hold*; by hand, the encoder is the command)
whose tail has the encoder still, within ``encoder_still_rad`` of where the hold ends.
Samples before the tail are the servo slewing (``moving``); a tail shorter than
``min_pause_s`` is not long enough for a trustworthy median (``short_pause``); a pot
sample far from the tail's median is a glitch (``pot_glitch``). Each pause gives one
point: the encoder's median and the mean of the pot's good samples (a mean, because the
ADC's whole counts dithered by its noise average to a fraction of a count, where a
median stays on the whole count: half a count is 0.006 rad of wheel near a lock).

Which side the wheel came from matters because of the coupling's free play: the encoder
sits half the play ahead of the wheel in the direction it last moved (behind it, where
hands turn the wheel and drag the servo). The direction is the sign of the encoder's
last motion larger than ``approach_rad`` before the pause (so a servo that overshoots
and comes back counts as coming back), anywhere before it, not only since its command
changed (by hand the command is the encoder, each hold a single reading, and a lock the
pot rails at leaves no rest to compare with); else the sign of the command's change (a
wheel held at its lock does not move at all), else unknown (``no_direction``). Right
after the sweep turns back, the servo first crosses the play without moving the wheel:
a pause that reverses the direction while the pot stays within ``pot_glitch_counts`` of
the pause before sits inside the play, on neither branch (``in_play``).

A pause where the encoder did not reach its command is *at a lock* (or the servo
stalled): still a valid point, since the wheel stands where the pot says and the
encoder half the play beyond it, but the end of the usable range. At the ends, a pause
the pot no longer follows (its counts change less than ``pot_follow_fraction`` of the
usual slope for the encoder's step) is past the pot's own travel, and a second pause at
the same lock adds nothing but weight at one point: both are refused (``past_travel``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Final

import numpy as np

from calibration.fit_checks import BoolArray, FloatArray, runs

POT_RAIL_LOW_COUNTS: Final = 0.0
POT_RAIL_HIGH_COUNTS: Final = 4095.0


@dataclass(frozen=True)
class PauseParams:
    command_tol_rad: float = 1e-3  # a command that changes less is the same hold
    encoder_still_rad: float = 0.005  # a few encoder ticks
    pot_glitch_counts: float = 5.0  # six times the pot's 0.8-count noise
    min_pause_s: float = 0.3
    approach_rad: float = 0.01  # above the servo's deadband
    follow_tol_rad: float = 0.05  # the deadband and a tick or two: more is a lock
    pot_follow_fraction: float = 0.3


@dataclass(frozen=True)
class Pause:
    """One pause of the sweep: a point of Fig. 17."""

    start_t_s: float
    end_t_s: float
    samples: int
    encoder_rad: float
    pot_counts: float
    commanded_rad: float
    direction: int  # +1: the encoder last moved up, -1: down
    at_lock: bool  # the encoder stopped short of its command
    used: bool = True  # False: refused (not following, or an outlier of the fit)


@dataclass(frozen=True)
class Pauses:
    pauses: tuple[Pause, ...]
    spans: tuple[tuple[int, int], ...]  # the samples each pause's medians came from
    refused: dict[str, BoolArray]  # per reason, in order of precedence


def find_pauses(
    t: FloatArray, encoder: FloatArray, pot: FloatArray, command: FloatArray, p: PauseParams
) -> Pauses:
    """The pauses of a time-ordered recording, and the samples refused on the way."""
    n = t.size
    railed = (pot <= POT_RAIL_LOW_COUNTS) | (pot >= POT_RAIL_HIGH_COUNTS)
    moving = np.zeros(n, dtype=np.bool_)
    short = np.zeros(n, dtype=np.bool_)
    glitch = np.zeros(n, dtype=np.bool_)
    no_direction = np.zeros(n, dtype=np.bool_)
    in_play = np.zeros(n, dtype=np.bool_)
    pauses: list[Pause] = []
    spans: list[tuple[int, int]] = []
    last_command = float(command[0])
    for start, stop in _holds(command, p.command_tol_rad):
        tail = _still_tail(encoder[start:stop], ~railed[start:stop], p.encoder_still_rad)
        moving[start : stop - tail] = True
        first = stop - tail
        if tail == 0 or t[stop - 1] - t[first] < p.min_pause_s:
            short[first:stop] = True
            continue
        span = slice(first, stop)
        usable = ~railed[span]
        if not usable.any():
            short[span] = True
            continue
        if 2 * np.count_nonzero(usable) < stop - first:
            # The pot stands on its rail here; what reads off it are glitches (a spike of
            # a few hundred counts off a railed 0 is in range). Their mean made a rest
            # 300 counts from the truth, and the map through it 6° of tyre angle off.
            glitch[span] = usable
            continue
        pot_median = float(np.median(pot[span][usable]))
        glitch[span] = usable & (np.abs(pot[span] - pot_median) > p.pot_glitch_counts)
        good = usable & ~glitch[span]
        if not good.any():  # no agreement at all: the pot is not steady, every sample off
            continue
        encoder_rad = float(np.median(encoder[span][good]))
        direction = _approach(encoder[:first], encoder_rad, p.approach_rad)
        if direction == 0:
            direction = int(np.sign(command[start] - last_command))
        last_command = float(command[start])
        if direction == 0:
            no_direction[span] = True
            continue
        pot_mean = float(np.mean(pot[span][good]))
        reversed_ = bool(pauses) and pauses[-1].direction != direction
        if reversed_ and abs(pot_mean - pauses[-1].pot_counts) <= p.pot_glitch_counts:
            in_play[span] = True
            continue
        pauses.append(
            Pause(
                start_t_s=float(t[first]),
                end_t_s=float(t[stop - 1]),
                samples=int(np.count_nonzero(good)),
                encoder_rad=encoder_rad,
                pot_counts=pot_mean,
                commanded_rad=float(command[start]),
                direction=direction,
                at_lock=abs(encoder_rad - float(command[start])) > p.follow_tol_rad,
            )
        )
        spans.append((first, stop))
    refused = {
        "pot_out_of_range": railed,
        "moving": moving,
        "short_pause": short,
        "pot_glitch": glitch,
        "no_direction": no_direction,
        "in_play": in_play,
    }
    return Pauses(tuple(pauses), tuple(spans), refused)


def not_following(pauses: tuple[Pause, ...], fraction: float) -> BoolArray:
    """Pauses at either end of each direction's sweep that the pot no longer follows."""
    out = np.zeros(len(pauses), dtype=np.bool_)
    for direction in (-1, 1):
        index = np.array([i for i, q in enumerate(pauses) if q.direction == direction])
        if index.size < 3:
            continue
        index = index[np.argsort([pauses[i].encoder_rad for i in index], kind="stable")]
        encoder = np.array([pauses[i].encoder_rad for i in index])
        pot = np.array([pauses[i].pot_counts for i in index])
        steps = np.diff(encoder)
        with np.errstate(divide="ignore", invalid="ignore"):
            slopes = np.where(np.abs(steps) > 0.0, np.diff(pot) / steps, 0.0)
        usual = float(np.median(slopes))
        if usual == 0.0:
            continue
        weak = slopes / usual < fraction  # a step the pot barely followed (or went back)
        low = 0
        while low < weak.size and weak[low]:
            out[index[low]] = True
            low += 1
        high = weak.size - 1
        while high >= low and weak[high]:
            out[index[high + 1]] = True
            high -= 1
    return out


def _holds(command: FloatArray, tol: float) -> list[tuple[int, int]]:
    """Index ranges of constant command."""
    changes = np.abs(np.diff(command)) > tol
    edges = [0, *(np.flatnonzero(changes) + 1).tolist(), command.size]
    return [(a, b) for a, b in itertools.pairwise(edges) if b > a]


def _still_tail(encoder: FloatArray, usable: BoolArray, tol: float) -> int:
    """How many samples at the end of a hold have the encoder within ``tol`` of its end."""
    if not usable.any():
        return 0
    quarter = max(1, encoder.size // 4)
    end = float(np.median(encoder[-quarter:]))
    stretches = runs(np.abs(encoder - end) <= tol)
    if not stretches or stretches[-1][1] != encoder.size:
        return 0
    return stretches[-1][1] - stretches[-1][0]


def _approach(before: FloatArray, at_rad: float, approach_rad: float) -> int:
    """Sign of the encoder's last motion larger than ``approach_rad`` towards ``at_rad``."""
    away = np.flatnonzero(np.abs(before - at_rad) > approach_rad)
    if away.size == 0:
        return 0
    return int(np.sign(at_rad - before[away[-1]]))
