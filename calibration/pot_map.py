"""The steering pot's map: raw counts to steering-wheel angle, as a polynomial.

``wheel_rad = sum(coeffs[i] * d**(i+1))`` with ``d = counts - centre``: no constant term,
because the centre reading means straight ahead by definition. Evaluating it, its slope
(the calibration file's monotonicity check) and fitting it to measured points are plain
numpy, shared by the file's validation, the daemon's conversions and every maneuver that
measures a map (the pot-map step, and the simulated vehicle's truth fitted the same way).

The pot-map step (Stanley et al., Fig. 17; :func:`fit_pot_map`, or
:class:`PotMapAccumulator` while the sweep runs): the vehicle stands and the wheel is
turned from full right to full left and back in half turns, resting after each, by the
servo (``commanded_wheel_rad`` its setpoint) or by hand (nothing commanded: the step
passes the encoder itself). The rests, their approach directions, the locks and what is
refused there are :mod:`calibration.pot_map_pauses`. The rests alone leave the map
loose: half turns give some seven positions each way, too few for the degree the map
needs near the locks, and it missed the truth by 0.12° of tyre angle between the rests
of the simulated vehicle's run. So the samples of the turning wheel are used too, once
the coupling's play is taken up, thinned and gated (:mod:`calibration.pot_map_motion`).
The joint fit of rests and motion samples, both sweep directions, which gives the
backlash and the map through the mid-branch points, is :mod:`calibration.pot_map_branches`;
it allows every power once the motion samples fill the sweep, so a centre a few counts
off shifts the map by its own error and does not bend it.

This module judges the result and turns it into the calibration file's values: the
polynomial, the centre (the pot-centre step's, given as an argument, else the reading at
encoder zero) and the valid range, the outermost rests used plus
``valid_margin_counts``. The figure to reach is the map within 0.2° of tyre angle over
that range; a rest, or the mean of any ``residual_group`` neighbouring motion samples of
one direction, further than half of that from the map (``max_residual_tyre_deg``)
refuses the fit. The backlash is signed: positive where the encoder leads the wheel (the
servo turns it), negative where it trails (the hands turn it and drag the servo).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from calibration.fit_checks import BoolArray, FloatArray, Verdict, sample_columns, tally, time_order
from calibration.pot_map_branches import BranchFit, BranchParams, BranchPoints, fit_branches
from calibration.pot_map_motion import MotionParams, judged_residuals, select_motion
from calibration.pot_map_pauses import Pause, PauseParams, find_pauses, not_following

# Up to degree 9: the inverse of a pot map with a cubic term near its lock needs it to
# reach a few mrad of steering-wheel angle (degree 5 cannot do better than ~0.02 rad).
MAX_POT_TO_WHEEL_COEFFS = 9


def wheel_rad_at(coeffs: Sequence[float], offset_counts: Any) -> Any:
    """``sum(coeffs[i] * d**(i+1))`` for ``d = offset_counts`` (a float or an array).

    A plain float goes through Horner's rule in Python, in the same order as numpy's
    ``polyval`` (so to the same bit): the control cycle inverts the map by bisection,
    sixty evaluations a cycle, and ``polyval`` on a scalar costs several microseconds each.
    """
    if isinstance(offset_counts, float | int):
        value = 0.0
        for coeff in reversed(coeffs):
            value = coeff + value * offset_counts
        return value * offset_counts
    return np.polynomial.polynomial.polyval(offset_counts, (0.0, *coeffs))


def wheel_slope_rad_per_count(coeffs: Sequence[float], offset_counts: FloatArray) -> FloatArray:
    """Derivative of :func:`wheel_rad_at` with respect to the counts."""
    derivative = [(i + 1) * c for i, c in enumerate(coeffs)]
    return np.asarray(np.polynomial.polynomial.polyval(offset_counts, derivative), np.float64)


def fit_pot_to_wheel_coeffs(
    offset_counts: FloatArray, wheel_rad: FloatArray, powers: Sequence[int]
) -> tuple[float, ...]:
    """Least squares ``wheel_rad ~ sum(c_p * d**p)`` over ``powers``, as file coefficients.

    Fitted in ``d / max|d|`` (with d**9 of a thousand counts the raw problem is singular),
    then scaled back. Returns ``coeff[i]`` for ``d**(i+1)``, zero where no power was fitted.
    """
    if max(powers) > MAX_POT_TO_WHEEL_COEFFS or min(powers) < 1:
        raise ValueError(f"powers must lie in 1..{MAX_POT_TO_WHEEL_COEFFS} (got {powers})")
    scale = float(np.max(np.abs(offset_counts)))
    design = np.stack([(offset_counts / scale) ** p for p in powers], axis=1)
    scaled, *_ = np.linalg.lstsq(design, wheel_rad, rcond=None)
    coeffs = [0.0] * max(powers)
    for power, coeff in zip(powers, scaled, strict=True):
        coeffs[power - 1] = float(coeff) / scale**power
    return tuple(coeffs)


# --- The pot-map maneuver (Fig. 17): from the sweep to the file's values. ---

POT_MAP_METHOD: Final = (
    "rests of a stationary half-turn sweep both ways, and the samples between them once "
    "the play is taken up (steady, below 3 rad/s, thinned to one per 0.05 rad); least "
    "squares of encoder angle on a polynomial of pot counts plus half the backlash times "
    "the direction, rests weighted by their samples; odd powers about the centre unless "
    "the points fill the sweep; one round of outliers; degree from the positions covered, "
    "lowered until monotonic (calibration.pot_map)"
)
POT_MAP_MIN_SAMPLES: Final = 10


@dataclass(frozen=True)
class PotMapParams:
    pauses: PauseParams = field(default_factory=PauseParams)
    motion: MotionParams = field(default_factory=MotionParams)
    branches: BranchParams = field(default_factory=BranchParams)
    min_pauses_per_direction: int = 4
    # More free play than this is a loose coupling to fix, not a number to calibrate.
    max_backlash_rad: float = 0.15
    max_residual_tyre_deg: float = 0.1  # half the map's 0.2° figure, for what lies between
    min_travel_rad: float = 0.5  # each side of centre: the calibration file's own minimum
    residual_group: int = 10  # the motion samples' residuals judged as means of this many


@dataclass(frozen=True)
class PotMapResult:
    pot_centre_counts: float | None  # None: no encoder zero inside the measured range
    centre_from: str  # "pot-centre step" or "encoder zero"
    pot_to_wheel_coeffs: tuple[float, ...]  # the file's: coeff[i] for d**(i+1)
    powers: tuple[int, ...]  # the powers fitted (fewer than asked if the points are few)
    positions: int  # distinct steering-wheel positions the points used cover
    motion_samples: int  # samples of the turning wheel used, besides the rests
    pot_valid_min_counts: int
    pot_valid_max_counts: int
    usable_min_counts: float  # the outermost pauses used
    usable_max_counts: float
    lock_at_min: bool  # the range ends at a lock (else: where the sweep turned back)
    lock_at_max: bool
    backlash_rad: float  # the two sweep directions' gap: < 0 if the encoder trails
    backlash_std_error_rad: float
    encoder_at_centre_rad: float  # the encoder's reading with the wheels straight
    monotonic: bool
    residual_rms_rad: float  # wheel rad: the rests and binned motion samples about the map
    residual_max_rad: float
    steering_ratio: float
    pauses: tuple[Pause, ...]
    samples: int
    accepted: int
    rejected: dict[str, int]
    method: str
    verdict: Verdict

    @property
    def residual_rms_tyre_deg(self) -> float:
        return math.degrees(self.residual_rms_rad / self.steering_ratio)

    @property
    def residual_max_tyre_deg(self) -> float:
        return math.degrees(self.residual_max_rad / self.steering_ratio)


@dataclass(frozen=True)
class PotMapCoverage:
    pauses_up: int
    pauses_down: int
    encoder_min_rad: float | None
    encoder_max_rad: float | None
    locks_seen: int  # pauses where the encoder stopped short of its command


def fit_pot_map(
    t_s: npt.ArrayLike,
    encoder_wheel_rad: npt.ArrayLike,
    pot_counts: npt.ArrayLike,
    commanded_wheel_rad: npt.ArrayLike,
    steering_ratio: float,
    pot_centre_counts: float | None = None,
    params: PotMapParams | None = None,
) -> PotMapResult:
    """The pot map from a stationary sweep; ValueError on malformed input.

    ``pot_centre_counts`` is the pot-centre step's result; without it the centre is the
    reading where the encoder reads zero (an encoder zeroed with the wheels straight).
    ``steering_ratio`` only turns wheel angles into the tyre degrees of the thresholds.
    """
    p = params or PotMapParams()
    if not (math.isfinite(steering_ratio) and steering_ratio > 0.0):
        raise ValueError(f"steering_ratio must be positive and finite: {steering_ratio}")
    if pot_centre_counts is not None and not math.isfinite(pot_centre_counts):
        raise ValueError(f"pot_centre_counts must be finite: {pot_centre_counts}")
    cols = time_order(
        sample_columns(
            {
                "t_s": t_s,
                "encoder_wheel_rad": encoder_wheel_rad,
                "pot_counts": pot_counts,
                "commanded_wheel_rad": commanded_wheel_rad,
            },
            POT_MAP_MIN_SAMPLES,
        )
    )
    t, encoder, pot = cols["t_s"], cols["encoder_wheel_rad"], cols["pot_counts"]
    found = find_pauses(t, encoder, pot, cols["commanded_wheel_rad"], p.pauses)
    past = not_following(found.pauses, p.pauses.pot_follow_fraction)
    pauses = [replace(q, used=not bad) for q, bad in zip(found.pauses, past, strict=True)]
    n = t.size
    in_rest = np.zeros(n, np.bool_)
    for a, b in found.spans:
        in_rest[a:b] = True
    railed = found.refused["pot_out_of_range"]
    rest_pots = [q.pot_counts for q in pauses if q.used]
    pot_range = (min(rest_pots), max(rest_pots)) if rest_pots else None
    motion = select_motion(t, encoder, pot, ~in_rest & ~railed, pot_range, p.motion)
    points = BranchPoints(
        pot_counts=np.concatenate([[q.pot_counts for q in pauses], pot[motion.index]]),
        encoder_rad=np.concatenate([[q.encoder_rad for q in pauses], encoder[motion.index]]),
        direction=np.concatenate([[float(q.direction) for q in pauses], motion.direction]),
        weight=np.concatenate([[float(q.samples) for q in pauses], np.ones(motion.index.size)]),
        used=np.concatenate([[q.used for q in pauses], np.ones(motion.index.size, np.bool_)]),
    )
    fit = fit_branches(points, pot_centre_counts, p.branches)
    outliers = fit.outliers if fit is not None else np.zeros(points.used.size, np.bool_)
    rests = len(pauses)
    pauses = [
        replace(q, used=q.used and not out) for q, out in zip(pauses, outliers[:rests], strict=True)
    ]
    past_samples, outlier_rests = np.zeros(n, np.bool_), np.zeros(n, np.bool_)
    for (a, b), bad, out in zip(found.spans, past, outliers[:rests], strict=True):
        past_samples[a:b], outlier_rests[a:b] = bad, out and not bad
    outlier_motion = np.zeros(n, np.bool_)
    outlier_motion[motion.index[outliers[rests:]]] = True
    glitch = (found.refused["pot_glitch"] & in_rest) | motion.refused.pop("pot_glitch")
    past_samples |= motion.refused.pop("past_travel")
    kept, rejected = tally(
        n,
        [
            ("pot_out_of_range", railed),
            ("pot_glitch", glitch),
            ("past_travel", past_samples),
            *motion.refused.items(),
            ("outlier_pause", outlier_rests),
            ("outlier_motion", outlier_motion),
        ],
    )
    judged = np.zeros(0)
    if fit is not None:
        k = fit.kept
        rest = np.arange(k.size) < rests
        judged = judged_residuals(
            fit.residuals_rad[k],
            points.encoder_rad[k],
            points.direction[k],
            rest[k],
            p.residual_group,
        )
    moved = int(np.count_nonzero(fit.kept[rests:])) if fit else 0
    return _result(
        fit, tuple(pauses), judged, moved, pot_centre_counts, steering_ratio, n, kept, rejected, p
    )


class PotMapAccumulator:
    """Samples as they arrive; ``coverage()`` during the sweep, ``fit()`` at the end."""

    def __init__(self, params: PotMapParams | None = None) -> None:
        self.params = params or PotMapParams()
        self._rows: list[tuple[float, float, float, float]] = []

    def reset(self) -> None:
        self._rows.clear()

    def update(
        self, t_s: float, encoder_wheel_rad: float, pot_counts: float, commanded_wheel_rad: float
    ) -> None:
        row = (float(t_s), float(encoder_wheel_rad), float(pot_counts), float(commanded_wheel_rad))
        if not all(math.isfinite(v) for v in row):
            raise ValueError(f"non-finite sample {row}: drop it upstream, do not send NaN")
        self._rows.append(row)

    def coverage(self) -> PotMapCoverage:
        if not self._rows:
            return PotMapCoverage(0, 0, None, None, 0)
        t, encoder, pot, command = np.asarray(self._rows).T
        order = np.argsort(t, kind="stable")
        found = find_pauses(
            t[order], encoder[order], pot[order], command[order], self.params.pauses
        ).pauses
        at = [q.encoder_rad for q in found]
        return PotMapCoverage(
            pauses_up=sum(1 for q in found if q.direction > 0),
            pauses_down=sum(1 for q in found if q.direction < 0),
            encoder_min_rad=min(at) if at else None,
            encoder_max_rad=max(at) if at else None,
            locks_seen=sum(1 for q in found if q.at_lock),
        )

    def fit(self, steering_ratio: float, pot_centre_counts: float | None = None) -> PotMapResult:
        data = np.asarray(self._rows).T if self._rows else np.zeros((4, 0))
        return fit_pot_map(
            data[0], data[1], data[2], data[3], steering_ratio, pot_centre_counts, self.params
        )


def _result(
    fit: BranchFit | None,
    pauses: tuple[Pause, ...],
    judged_residuals_rad: FloatArray,
    motion_samples: int,
    given_centre: float | None,
    steering_ratio: float,
    samples: int,
    kept: BoolArray,
    rejected: dict[str, int],
    p: PotMapParams,
) -> PotMapResult:
    used = [q for q in pauses if q.used]
    up = sum(1 for q in used if q.direction > 0)
    down = len(used) - up
    reasons: list[str] = []
    if min(up, down) < p.min_pauses_per_direction:
        reasons.append(
            f"{up} pause(s) sweeping up and {down} down, at least {p.min_pauses_per_direction} "
            "each way needed (the backlash is the gap between the two)"
        )
    common: dict[str, Any] = {
        "steering_ratio": steering_ratio,
        "pauses": pauses,
        "samples": samples,
        "accepted": int(np.count_nonzero(kept)),
        "rejected": rejected,
        "method": POT_MAP_METHOD,
    }
    if fit is None or not used:
        return PotMapResult(
            pot_centre_counts=None,
            centre_from="none",
            pot_to_wheel_coeffs=(),
            powers=(),
            positions=0,
            motion_samples=0,
            pot_valid_min_counts=0,
            pot_valid_max_counts=0,
            usable_min_counts=math.nan,
            usable_max_counts=math.nan,
            lock_at_min=False,
            lock_at_max=False,
            backlash_rad=math.nan,
            backlash_std_error_rad=math.nan,
            encoder_at_centre_rad=math.nan,
            monotonic=False,
            residual_rms_rad=math.nan,
            residual_max_rad=math.nan,
            verdict=Verdict.from_reasons(
                [*reasons, *(["fewer than 4 usable points: nothing to fit"] if fit is None else [])]
            ),
            **common,
        )
    residual_rms = float(np.sqrt(np.mean(judged_residuals_rad**2)))
    residual_max = float(np.max(np.abs(judged_residuals_rad)))
    backlash = 2.0 * fit.half_backlash_rad
    low, high = fit.valid_counts
    centre = fit.centre_counts
    if centre is None:
        reasons.append(
            "no reading where the encoder reads zero could be located (it reads zero "
            "nowhere in the swept range, or the map's zero did not settle): give the "
            "centre from the pot-centre step"
        )
    elif not low < centre < high:
        reasons.append(f"the centre {centre:.1f} lies outside the valid range {low}..{high}")
    else:
        for name, end in (("min", low), ("max", high)):
            travel = abs(float(wheel_rad_at(fit.coeffs, end - centre)))
            if travel < p.min_travel_rad:
                reasons.append(
                    f"only {travel:.2f} rad of steering wheel between the centre and the "
                    f"valid {name}, at least {p.min_travel_rad} needed: sweep further"
                )
    if not fit.monotonic:
        reasons.append("no polynomial up to the asked degree is monotonic over the range")
    if abs(backlash) > p.max_backlash_rad:
        reasons.append(
            f"{abs(backlash):.3f} rad of backlash between the sweep directions, more than "
            f"{p.max_backlash_rad}: tighten the coupling"
        )
    residual_max_deg = math.degrees(residual_max / steering_ratio)
    if residual_max_deg > p.max_residual_tyre_deg:
        reasons.append(
            f"the map misses a rest or a stretch of the turning wheel by {residual_max_deg:.3f}° "
            f"of tyre angle, more than {p.max_residual_tyre_deg}°"
        )
    ends = [min(used, key=lambda q: q.pot_counts), max(used, key=lambda q: q.pot_counts)]
    return PotMapResult(
        pot_centre_counts=centre,
        centre_from="pot-centre step" if given_centre is not None else "encoder zero",
        pot_to_wheel_coeffs=fit.coeffs,
        powers=fit.powers,
        positions=fit.positions,
        motion_samples=motion_samples,
        pot_valid_min_counts=low,
        pot_valid_max_counts=high,
        usable_min_counts=ends[0].pot_counts,
        usable_max_counts=ends[1].pot_counts,
        lock_at_min=ends[0].at_lock,
        lock_at_max=ends[1].at_lock,
        backlash_rad=backlash,
        backlash_std_error_rad=2.0 * fit.half_backlash_se_rad,
        encoder_at_centre_rad=fit.offset_rad,
        monotonic=fit.monotonic,
        residual_rms_rad=residual_rms,
        residual_max_rad=residual_max,
        verdict=Verdict.from_reasons(reasons),
        **common,
    )
