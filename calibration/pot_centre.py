"""The pot's straight-ahead reading, from driving straight along a visual reference.

Stanley et al.'s first tuning step: "drive the vehicle on a straight line along a visual
reference path, measure the steering potentiometer values, and average those values".
Every tyre angle the daemon reports or commands is measured from this reading, so an
error here is a steady pull to one side that no check downstream can see.

The method (:func:`fit_pot_centre`):

1. Samples are refused, each for the first reason that applies: the pot at or past its
   rail (unplugged or broken, not a steering angle); a poor GNSS/INS fix (its heading rate
   is not to be trusted), where a fix-quality column is given; too slow (below
   ``min_speed_mps`` a heading rate says little about the wheels: the same tyre angle
   gives a yaw rate proportional to speed, and at a walk the INS's rate noise is as large
   as the signal); turning (``|yaw rate|`` above ``max_yaw_rate_rad_per_s``); the wheel
   moving (faster than ``max_steer_rate_rad_per_s``, where a steering-rate column is
   given: mid-correction the pot leads the yaw rate, so the two do not describe the same
   moment).
2. The samples left form runs; a gap longer than ``max_gap_s`` ends a run. A run shorter
   than ``min_segment_s`` or ``min_segment_m`` is refused (``short_segment``): a driver
   holding a line corrects every few seconds, and only an average over several
   corrections is the centre rather than one side of a weave.
3. Each segment gives one estimate of the centre: its mean pot reading, less what its
   net turning explains. "Straight" by a yaw-rate gate still lets a segment curve gently
   (a vehicle settling onto the line after a turn holds a small angle for many seconds:
   0.004 rad/s at 3 m/s is 0.17° of the Husky's tyre angle, more than the figure). The segments'
   samples give the pot's slope against curvature (yaw rate / speed, smoothed over
   ``curvature_window_s`` so the INS's rate noise does not flatten it), one slope pooled
   over every segment's deviations from its own means; each segment's estimate is its
   mean pot at zero curvature along that slope. No vehicle model enters: the slope is
   measured, so a wrong wheelbase or k ratio cannot bias the centre. Their median is robust
   to one bad segment (a crowned or cambered stretch, a gust); a segment further from it
   than ``outlier_sigmas`` robust σ (and than the spread threshold, so ordinary spread is
   never cut) is dropped (``outlier_segment``). The centre is the distance-weighted mean
   of the segments kept: longer segments average more corrections.
4. The verdict: at least ``min_segments`` segments (one segment cannot show its own
   bias), ``min_total_m`` of straight driving, and the segments' means agreeing within
   ``max_spread_tyre_deg`` (their standard deviation, in tyre degrees through the slope
   the caller gives). The figure to reach is the centre within 0.1° of tyre angle; with
   three segments spread 0.2° the mean's standard error is 0.12°, so a spread above that
   means the segments disagree more than the figure allows.

Samples may stream in through :class:`PotCentreAccumulator` (``coverage()`` shows the
segments found so far while driving), or be given at once to :func:`fit_pot_centre`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from calibration.fit_checks import (
    BoolArray,
    FloatArray,
    Verdict,
    mad_sigma,
    optional_column,
    runs,
    sample_columns,
    tally,
    time_order,
)

METHOD: Final = (
    "straight segments by yaw rate, speed, steering rate and fix gates; per-segment mean "
    "pot at zero curvature (pooled pot-vs-curvature slope); outlier segments dropped about "
    "the median; distance-weighted mean (calibration.pot_centre)"
)
MIN_SAMPLES: Final = 10
POT_RAIL_LOW_COUNTS: Final = 0.0
POT_RAIL_HIGH_COUNTS: Final = 4095.0  # 12-bit ADC: a reading at a rail is not an angle
REASONS: Final = (
    "pot_out_of_range",
    "fix_quality",
    "slow",
    "turning",
    "steering_moving",
    "short_segment",
    "outlier_segment",
)


@dataclass(frozen=True)
class PotCentreParams:
    max_yaw_rate_rad_per_s: float = 0.02  # ~1°/s: a few times a tactical INS's rate noise
    min_speed_mps: float = 1.0
    max_steer_rate_rad_per_s: float = 0.2  # steering wheel; only with a steering-rate column
    max_gap_s: float = 0.5  # ten missed samples at 20 Hz end a segment
    min_segment_s: float = 5.0
    min_segment_m: float = 10.0
    min_segments: int = 3
    min_total_m: float = 100.0
    max_spread_tyre_deg: float = 0.2
    outlier_sigmas: float = 3.0
    curvature_window_s: float = 1.0  # the driver's corrections take seconds; noise does not


@dataclass(frozen=True)
class StraightSegment:
    start_t_s: float
    end_t_s: float
    samples: int
    distance_m: float
    mean_counts: float
    std_counts: float  # the pot's spread within the segment (the driver's corrections)
    mean_yaw_rate_rad_per_s: float
    mean_curvature_per_m: float
    centre_counts: float  # the mean at zero curvature: this segment's estimate
    used: bool  # False: dropped as an outlier


@dataclass(frozen=True)
class PotCentreResult:
    centre_counts: float | None  # None when no segment was found
    counts_per_tyre_deg: float
    segments: tuple[StraightSegment, ...]
    segments_used: int
    distance_m: float  # of the segments used
    curvature_slope_counts_m: float  # pot counts per 1/m of curvature, pooled
    spread_counts: float  # std of the used segments' estimates (0 with fewer than two)
    within_segment_std_counts: float  # rms of the used segments' own std
    residual_rms_counts: float  # used samples about the centre
    residual_max_counts: float
    samples: int
    accepted: int
    rejected: dict[str, int]
    method: str
    verdict: Verdict
    params: PotCentreParams = field(repr=False)

    def tyre_deg(self, counts: float) -> float:
        """A spread or residual in counts as tyre degrees (e.g. a segment's ``std_counts``)."""
        return counts / abs(self.counts_per_tyre_deg)

    @property
    def spread_tyre_deg(self) -> float:
        return self.tyre_deg(self.spread_counts)

    @property
    def within_segment_std_tyre_deg(self) -> float:
        return self.tyre_deg(self.within_segment_std_counts)

    @property
    def standard_error_tyre_deg(self) -> float:
        """The centre's own uncertainty: the segments' spread over √segments."""
        return self.spread_tyre_deg / max(1.0, float(np.sqrt(self.segments_used)))


@dataclass(frozen=True)
class PotCentreCoverage:
    """How far the maneuver has got: what the fit would find in the samples so far."""

    segments: int
    distance_m: float
    segments_needed: int
    distance_needed_m: float

    @property
    def complete(self) -> bool:
        return self.segments >= self.segments_needed and self.distance_m >= self.distance_needed_m


@dataclass(frozen=True)
class _Segmentation:
    kept: BoolArray
    rejected: dict[str, int]
    segments: tuple[StraightSegment, ...]
    centre_counts: float | None
    curvature_slope_counts_m: float


def fit_pot_centre(
    t_s: npt.ArrayLike,
    pot_counts: npt.ArrayLike,
    yaw_rate_rad_per_s: npt.ArrayLike,
    speed_mps: npt.ArrayLike,
    counts_per_tyre_deg: float,
    steer_rate_rad_per_s: npt.ArrayLike | None = None,
    fix_ok: npt.ArrayLike | None = None,
    params: PotCentreParams | None = None,
) -> PotCentreResult:
    """The straight-ahead pot reading from straight driving; ValueError on malformed input.

    ``counts_per_tyre_deg`` is the pot's slope at the centre (its sign does not matter),
    from the pot map or the installation's nominal one: it turns counts into the tyre
    degrees the thresholds and the figure are stated in. ``fix_ok`` is non-zero where the
    fix is good enough to trust its heading rate.
    """
    p = params or PotCentreParams()
    if not np.isfinite(counts_per_tyre_deg) or counts_per_tyre_deg == 0.0:
        raise ValueError(f"counts_per_tyre_deg must be finite and non-zero: {counts_per_tyre_deg}")
    cols = _columns(t_s, pot_counts, yaw_rate_rad_per_s, speed_mps, steer_rate_rad_per_s, fix_ok)
    seg = _segment(cols, p, p.max_spread_tyre_deg * abs(counts_per_tyre_deg), MIN_SAMPLES)
    pot = cols["pot_counts"]
    used = [s for s in seg.segments if s.used]
    centre = seg.centre_counts
    spread = float(np.std([s.centre_counts for s in used], ddof=1)) if len(used) > 1 else 0.0
    within = float(np.sqrt(np.mean([s.std_counts**2 for s in used]))) if used else 0.0
    residuals = pot[seg.kept] - centre if centre is not None else np.zeros(0)
    distance = float(sum(s.distance_m for s in used))
    slope = abs(counts_per_tyre_deg)
    reasons: list[str] = []
    if len(used) < p.min_segments:
        reasons.append(f"{len(used)} straight segment(s), at least {p.min_segments} needed")
    if distance < p.min_total_m:
        reasons.append(f"{distance:.0f} m driven straight, at least {p.min_total_m:.0f} m needed")
    if spread / slope > p.max_spread_tyre_deg:
        reasons.append(
            f"the segments disagree: their estimates spread {spread / slope:.3f}° of tyre angle, "
            f"more than {p.max_spread_tyre_deg}° (a crowned road, or not driven straight?)"
        )
    return PotCentreResult(
        centre_counts=centre,
        counts_per_tyre_deg=counts_per_tyre_deg,
        segments=seg.segments,
        segments_used=len(used),
        distance_m=distance,
        curvature_slope_counts_m=seg.curvature_slope_counts_m,
        spread_counts=spread,
        within_segment_std_counts=within,
        residual_rms_counts=float(np.sqrt(np.mean(residuals**2))) if residuals.size else 0.0,
        residual_max_counts=float(np.max(np.abs(residuals))) if residuals.size else 0.0,
        samples=pot.size,
        accepted=int(np.count_nonzero(seg.kept)),
        rejected=seg.rejected,
        method=METHOD,
        verdict=Verdict.from_reasons(reasons),
        params=p,
    )


class PotCentreAccumulator:
    """Samples as they arrive; ``coverage()`` while driving, ``fit()`` at the end."""

    def __init__(self, params: PotCentreParams | None = None) -> None:
        self.params = params or PotCentreParams()
        self._rows: list[tuple[float, ...]] = []

    def reset(self) -> None:
        self._rows.clear()

    def update(
        self,
        t_s: float,
        pot_counts: float,
        yaw_rate_rad_per_s: float,
        speed_mps: float,
        steer_rate_rad_per_s: float = 0.0,
        fix_ok: bool = True,
    ) -> None:
        row = (t_s, pot_counts, yaw_rate_rad_per_s, speed_mps, steer_rate_rad_per_s, fix_ok)
        values = tuple(float(v) for v in row)
        if not all(np.isfinite(values)):
            raise ValueError(f"non-finite sample {row}: drop it upstream, do not send NaN")
        self._rows.append(values)

    def coverage(self) -> PotCentreCoverage:
        p = self.params
        found: tuple[StraightSegment, ...] = ()
        if self._rows:
            data = np.asarray(self._rows).T
            cols = _columns(data[0], data[1], data[2], data[3], data[4], data[5])
            # no slope yet to judge outliers by: every segment counts while driving
            found = _segment(cols, p, np.inf, 0).segments
        return PotCentreCoverage(
            segments=sum(1 for s in found if s.used),
            distance_m=float(sum(s.distance_m for s in found if s.used)),
            segments_needed=p.min_segments,
            distance_needed_m=p.min_total_m,
        )

    def fit(self, counts_per_tyre_deg: float) -> PotCentreResult:
        data = np.asarray(self._rows).T if self._rows else np.zeros((6, 0))
        return fit_pot_centre(
            data[0], data[1], data[2], data[3], counts_per_tyre_deg, data[4], data[5], self.params
        )


def _columns(
    t_s: npt.ArrayLike,
    pot_counts: npt.ArrayLike,
    yaw_rate_rad_per_s: npt.ArrayLike,
    speed_mps: npt.ArrayLike,
    steer_rate_rad_per_s: npt.ArrayLike | None,
    fix_ok: npt.ArrayLike | None,
) -> dict[str, FloatArray]:
    cols = sample_columns(
        {
            "t_s": t_s,
            "pot_counts": pot_counts,
            "yaw_rate_rad_per_s": yaw_rate_rad_per_s,
            "speed_mps": speed_mps,
        },
        min_samples=0,
    )
    n = cols["t_s"].size
    cols["steer_rate_rad_per_s"] = optional_column(
        "steer_rate_rad_per_s", steer_rate_rad_per_s, n, 0.0
    )
    cols["fix_ok"] = optional_column("fix_ok", fix_ok, n, 1.0)
    sample_columns(cols, min_samples=0)  # the optional columns' lengths
    return cols


def _segment(
    cols: dict[str, FloatArray], p: PotCentreParams, outlier_floor_counts: float, min_samples: int
) -> _Segmentation:
    if cols["t_s"].size < min_samples:
        raise ValueError(
            f"too few samples: {cols['t_s'].size}, the fit needs at least {min_samples}"
        )
    cols = time_order(cols)
    t, pot, speed = cols["t_s"], cols["pot_counts"], cols["speed_mps"]
    gates: list[tuple[str, BoolArray]] = [
        ("pot_out_of_range", (pot <= POT_RAIL_LOW_COUNTS) | (pot >= POT_RAIL_HIGH_COUNTS)),
        ("fix_quality", cols["fix_ok"] == 0.0),
        ("slow", np.abs(speed) < p.min_speed_mps),
        ("turning", np.abs(cols["yaw_rate_rad_per_s"]) > p.max_yaw_rate_rad_per_s),
        ("steering_moving", np.abs(cols["steer_rate_rad_per_s"]) > p.max_steer_rate_rad_per_s),
    ]
    eligible, _ = tally(t.size, gates)
    short = np.zeros(t.size, dtype=np.bool_)
    bounds: list[tuple[int, int]] = []
    for start, stop in _split_at_gaps(eligible, t, p.max_gap_s):
        duration = t[stop - 1] - t[start]
        if duration < p.min_segment_s or _distance_m(t, speed, start, stop) < p.min_segment_m:
            short[start:stop] = True
        else:
            bounds.append((start, stop))
    curvature = _smoothed_curvature(cols, bounds, p.curvature_window_s)
    slope = _pooled_slope(pot, curvature, bounds)
    means = np.array([pot[a:b].mean() for a, b in bounds])
    mean_curvatures = np.array([curvature[a:b].mean() for a, b in bounds])
    estimates = means - slope * mean_curvatures
    used = _inliers(estimates, p.outlier_sigmas, outlier_floor_counts)
    outlier = np.zeros(t.size, dtype=np.bool_)
    for (a, b), keep in zip(bounds, used, strict=True):
        outlier[a:b] = not keep
    kept, rejected = tally(t.size, [*gates, ("short_segment", short), ("outlier_segment", outlier)])
    segments = tuple(
        StraightSegment(
            start_t_s=float(t[a]),
            end_t_s=float(t[b - 1]),
            samples=b - a,
            distance_m=_distance_m(t, speed, a, b),
            mean_counts=float(means[j]),
            std_counts=float(pot[a:b].std()),
            mean_yaw_rate_rad_per_s=float(cols["yaw_rate_rad_per_s"][a:b].mean()),
            mean_curvature_per_m=float(mean_curvatures[j]),
            centre_counts=float(estimates[j]),
            used=bool(used[j]),
        )
        for j, (a, b) in enumerate(bounds)
    )
    weights = np.array([s.distance_m for s in segments if s.used])
    centre = None
    if weights.size:
        total = float(weights.sum())
        centre = float(np.average(estimates[used], weights=weights if total > 0.0 else None))
    return _Segmentation(kept, rejected, segments, centre, slope)


def _split_at_gaps(mask: BoolArray, t: FloatArray, max_gap_s: float) -> list[tuple[int, int]]:
    pieces: list[tuple[int, int]] = []
    for start, stop in runs(mask):
        cuts = start + 1 + np.flatnonzero(np.diff(t[start:stop]) > max_gap_s)
        edges = [start, *cuts.tolist(), stop]
        pieces.extend(itertools.pairwise(edges))
    return pieces


def _smoothed_curvature(
    cols: dict[str, FloatArray], bounds: list[tuple[int, int]], window_s: float
) -> FloatArray:
    """Yaw rate over speed, a centred moving mean of ``window_s`` within each segment."""
    t, speed = cols["t_s"], np.abs(cols["speed_mps"])
    raw = cols["yaw_rate_rad_per_s"] / np.maximum(speed, 1e-6)
    smoothed = raw.copy()
    for a, b in bounds:
        if b - a < 3:
            continue
        width = max(1, round(window_s / float(np.median(np.diff(t[a:b])))))
        kernel = np.ones(min(width, b - a))
        total = np.convolve(raw[a:b], kernel, mode="same")
        smoothed[a:b] = total / np.convolve(np.ones(b - a), kernel, mode="same")
    return smoothed


def _pooled_slope(pot: FloatArray, curvature: FloatArray, bounds: list[tuple[int, int]]) -> float:
    """Least squares slope of pot against curvature, each segment about its own means."""
    covariance = variance = 0.0
    for a, b in bounds:
        dk = curvature[a:b] - curvature[a:b].mean()
        covariance += float(np.dot(dk, pot[a:b] - pot[a:b].mean()))
        variance += float(np.dot(dk, dk))
    return covariance / variance if variance > 0.0 else 0.0


def _distance_m(t: FloatArray, speed: FloatArray, start: int, stop: int) -> float:
    v = np.abs(speed[start:stop])
    return float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t[start:stop])))


def _inliers(means: FloatArray, sigmas: float, floor_counts: float) -> BoolArray:
    """Segments within ``sigmas`` robust σ of the median, never closer than the floor."""
    if means.size < 3:  # two segments cannot say which one is the outlier
        return np.ones(means.size, dtype=np.bool_)
    limit = max(sigmas * mad_sigma(means), floor_counts)
    return np.asarray(np.abs(means - np.median(means)) <= limit)
