"""What a GNSS pose is worth at the control cycle's time: brought forward, and judged.

`extrapolate` moves the latest `GnssPose` from its measurement time to ``now_s`` along an
arc, so the tracker steers by where the vehicle is rather than where it was a latency ago.
`fix_verdict` is the safety layer's question, "may automatic steering use this fix now?",
answered deny by default: whatever the parameters require and the pose does not show (no
GST, no satellite count, no heading) is a refusal, worded for the operator and for the
daemon's refusal list.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from appliance.localization.compound import wrap_angle_rad
from appliance.localization.gnss_pose import GnssNoFix, GnssPose, HeadingSource, SigmaSource
from drivers.geometry import Pose2D
from drivers.gnss.sentences import FixQuality

QUALITY_LABELS: dict[FixQuality, str] = {
    FixQuality.INVALID: "invalid",
    FixQuality.GPS: "GPS",
    FixQuality.DGPS: "DGPS",
    FixQuality.PPS: "PPS",
    FixQuality.RTK_FIXED: "RTK fixed",
    FixQuality.RTK_FLOAT: "RTK float",
    FixQuality.DEAD_RECKONING: "dead reckoning",
    FixQuality.MANUAL: "manual",
    FixQuality.SIMULATION: "simulation",
}


@dataclass(frozen=True)
class ExtrapolatedPose:
    """A pose brought forward to ``time_s``; σ grown with the extrapolation (None stays
    unknown)."""

    pose: Pose2D
    time_s: float
    extrapolation_s: float
    heading_source: HeadingSource
    sigma_east_m: float | None
    sigma_north_m: float | None
    sigma_worst_m: float | None


def extrapolate(
    pose: GnssPose,
    now_s: float,
    max_extrapolation_s: float,
    *,
    sigma_growth_mps: float = 0.2,
) -> ExtrapolatedPose | None:
    """The pose at ``now_s`` at constant speed and yaw rate (an arc; a line at yaw rate 0 or
    unknown), or None: beyond ``max_extrapolation_s``, backwards in time (a broken clock),
    without a heading, or without a speed to move by.

    The chord of an arc through angle θ = ω·dt has length v·dt·sinc(θ/2) and points along
    the travel direction turned by θ/2: exact for any ω, with no division by ω near 0.
    The travel direction is the course over ground when moving (it includes sideslip and
    reversing), else the heading. σ grows by ``sigma_growth_mps`` × dt on each axis:
    linear, and more than the ½·a·dt² an unmodelled acceleration adds over short spans.
    """
    dt_s = now_s - pose.measurement_time_s
    if not (math.isfinite(dt_s) and 0.0 <= dt_s <= max_extrapolation_s) or pose.yaw_rad is None:
        return None
    if pose.speed_mps is None and dt_s > 0.0:
        return None
    speed_mps = pose.speed_mps or 0.0
    turn_rad = (pose.yaw_rate_rad_per_s or 0.0) * dt_s
    travel_rad = pose.course_yaw_rad if pose.course_yaw_rad is not None else pose.yaw_rad
    half_rad = turn_rad / 2.0
    sinc = 1.0 - half_rad**2 / 6.0 if abs(half_rad) < 1e-4 else math.sin(half_rad) / half_rad
    chord_m = speed_mps * dt_s * sinc
    east_m = pose.east_m + chord_m * math.cos(travel_rad + half_rad)
    north_m = pose.north_m + chord_m * math.sin(travel_rad + half_rad)
    if not (math.isfinite(east_m) and math.isfinite(north_m)):
        return None  # only a hand-built pose can get here: the assembler's are plausible
    growth_m = sigma_growth_mps * dt_s

    def grown(sigma_m: float | None) -> float | None:
        return None if sigma_m is None else sigma_m + growth_m

    return ExtrapolatedPose(
        pose=Pose2D(east_m, north_m, wrap_angle_rad(pose.yaw_rad + turn_rad)),
        time_s=now_s,
        extrapolation_s=dt_s,
        heading_source=pose.heading_source,
        sigma_east_m=grown(pose.sigma_east_m),
        sigma_north_m=grown(pose.sigma_north_m),
        sigma_worst_m=grown(pose.sigma_worst_m),
    )


@dataclass(frozen=True)
class FixVerdictParams:
    """What a fix must show for automatic steering. Defaults are for RTK-grade tracking
    (the paper's 0.14 m RMS needs a σ well under it). ``max_sigma_m`` None and
    ``min_satellites`` 0 switch those checks off; nothing else can be switched off."""

    max_fix_age_s: float = 0.5
    max_sigma_m: float | None = 0.15
    accepted_qualities: tuple[FixQuality, ...] = (FixQuality.RTK_FIXED, FixQuality.RTK_FLOAT)
    min_satellites: int = 6
    require_heading: bool = True
    accept_course_as_heading: bool = False  # course is the heading only when driving forward

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_fix_age_s) and self.max_fix_age_s > 0.0):
            raise ValueError(f"max_fix_age_s must be positive and finite: {self.max_fix_age_s}")
        if self.max_sigma_m is not None and not (
            math.isfinite(self.max_sigma_m) and self.max_sigma_m > 0.0
        ):
            raise ValueError(f"max_sigma_m must be positive and finite: {self.max_sigma_m}")
        if not self.accepted_qualities or FixQuality.INVALID in self.accepted_qualities:
            raise ValueError(f"accepted_qualities must name real fixes: {self.accepted_qualities}")
        if self.min_satellites < 0:
            raise ValueError(f"min_satellites must not be negative: {self.min_satellites}")


@dataclass(frozen=True)
class FixVerdict:
    """``reason`` is the first refusal ("" when ok); ``reasons`` all of them, in the order
    an operator should fix them: a fix at all, a fresh one, a good one, a heading."""

    ok: bool
    reason: str
    reasons: tuple[str, ...]


def fix_verdict(
    pose: GnssPose | GnssNoFix | None, now_s: float, params: FixVerdictParams
) -> FixVerdict:
    """May automatic steering use this fix at ``now_s``? ``pose`` is the latest the
    assembler emitted (None: none yet)."""
    if not isinstance(pose, GnssPose):
        return _refuse(["no fix"])
    reasons: list[str] = []
    age_s = now_s - pose.measurement_time_s
    if not math.isfinite(age_s):
        reasons.append("fix lost: no valid time to judge its age")
    elif age_s < 0.0:
        # Measurement time is receive time minus latency: never ahead of a sane clock.
        reasons.append(f"fix lost: fix time {-age_s:.2f} s ahead of now")
    elif age_s > params.max_fix_age_s:
        age = _exceeding(age_s, params.max_fix_age_s, 1)
        reasons.append(f"fix lost: last fix {age} s ago (limit {params.max_fix_age_s:g} s)")
    if pose.quality not in params.accepted_qualities:
        need = join_labels([QUALITY_LABELS[q] for q in params.accepted_qualities])
        reasons.append(f"fix degraded: quality {QUALITY_LABELS[pose.quality]} (need {need})")
    if params.min_satellites > 0 and (
        pose.satellites is None or pose.satellites < params.min_satellites
    ):
        count = "unknown" if pose.satellites is None else str(pose.satellites)
        reasons.append(f"too few satellites: {count} (need {params.min_satellites})")
    if params.max_sigma_m is not None:
        reasons += _sigma_reasons(pose, params.max_sigma_m)
    if params.require_heading:
        if pose.heading_source is HeadingSource.MISSING or pose.yaw_rad is None:
            reasons.append("no heading")
        elif pose.heading_source is HeadingSource.COURSE and not params.accept_course_as_heading:
            reasons.append("no heading: course over ground only")
    return _refuse(reasons) if reasons else FixVerdict(ok=True, reason="", reasons=())


def _sigma_reasons(pose: GnssPose, limit_m: float) -> list[str]:
    sigma_m = pose.sigma_worst_m
    if pose.sigma_source is SigmaSource.MISSING or sigma_m is None or not math.isfinite(sigma_m):
        return [f"fix degraded: σ unknown (limit {limit_m:g} m)"]
    if sigma_m <= limit_m:
        return []
    how = " estimated from HDOP" if pose.sigma_source is SigmaSource.HDOP else ""
    return [f"fix degraded: σ {_exceeding(sigma_m, limit_m, 2)} m{how} (limit {limit_m:g} m)"]


def _refuse(reasons: list[str]) -> FixVerdict:
    return FixVerdict(ok=False, reason=reasons[0], reasons=tuple(reasons))


def _exceeding(value: float, limit: float, decimals: int) -> str:
    """``value`` with as many decimals (from ``decimals``, up to 4) as it takes to read as
    more than ``limit``: "0.5 s ago (limit 0.5 s)" would contradict itself."""
    for places in range(decimals, 5):
        text = f"{value:.{places}f}"
        if float(text) > limit:
            return text
    return f"{value:.4f}"


def join_labels(labels: list[str]) -> str:
    """ "RTK fixed or float", "GPS, DGPS or RTK fixed": a shared first word is said once."""
    words = [label.split(" ", 1) for label in labels]
    if len(labels) > 1 and all(len(w) == 2 and w[0] == words[0][0] for w in words):
        return f"{words[0][0]} {join_labels([w[1] for w in words])}"
    return labels[0] if len(labels) == 1 else f"{', '.join(labels[:-1])} or {labels[-1]}"
