"""NMEA events to a timed vehicle pose: one `GnssPose` per receiver epoch.

A receiver reports one measurement epoch as a burst of sentences (GGA, RMC/VTG, HDT/THS,
GST). GGA, RMC and GST carry the epoch's UTC time of day, so they are matched by it; VTG,
HDT and THS carry none, so they belong to the epoch whose burst they arrive in (within
``epoch_window_s`` of its first sentence; the latest wins). A timed sentence of an epoch
already closed is late and dropped, never mixed into the newer one: a heading from one epoch
with a position from another is a pose the vehicle never had.

An epoch is emitted as soon as it holds every sentence type the receiver sent in its last
few epochs (learned, so no configuration has to list them), or when its window has passed
(`expire`, called every control cycle) or the next epoch begins. So a dropped line costs
nothing but the missing field, and a receiver that changes its output costs at most one
window of delay.

The pose is stamped with its *measurement* time: the GGA's receive time in the daemon's
monotonic seconds minus the receiver's configured latency, so the controller can bring it
forward to its own cycle instead of steering by where the vehicle was.

Frames: ENU metres around the `LocalFrame` origin, yaw counter-clockwise from east. NMEA
directions are clockwise from *true* north at the antenna, whose meridian is turned by
Δλ·sin φ against the origin's (0.007° at 1 km east at 42° N; converted anyway, it is free).
`appliance.localization.gnss_quality` brings a pose to the control cycle and judges it.
The pose is the antenna's (or the INS reference point's); the lever arm to the vehicle's
centre is the consumer's to apply.
"""

from __future__ import annotations

import enum
import math
from collections import Counter, deque
from dataclasses import dataclass, field

from appliance.localization.compound import wrap_angle_rad
from appliance.localization.local_frame import LocalFrame
from drivers.gnss.sentences import (
    FixQuality,
    GgaFix,
    GstError,
    Heading,
    NmeaEvent,
    RmcFix,
    VtgVelocity,
)

_DAY_S = 86400.0
_TIMED_KINDS = frozenset({"GGA", "RMC", "GST"})
_KINDS: dict[type, str] = {GgaFix: "GGA", RmcFix: "RMC", VtgVelocity: "VTG", GstError: "GST"}
_PLAUSIBLE_ALTITUDE_M = 1e5  # beyond it a GGA altitude is a fault, not a height
_PLAUSIBLE_SPEED_MPS = 500.0  # likewise a speed over ground (NMEA's own limit is 999 kn)
_MIN_RATE_INTERVAL_S = 1e-3  # headings closer in time than this say nothing about a rate


class HeadingSource(enum.Enum):
    TRUE_HEADING = "true heading"  # HDT or THS: where the vehicle points
    COURSE = "course over ground"  # RMC/VTG while moving: where it goes (assumes forward)
    MISSING = "missing"


class SigmaSource(enum.Enum):
    GST = "GST"  # the receiver's own error estimate
    HDOP = "estimated from HDOP"  # HDOP × a conservative UERE: no GST in the epoch
    MISSING = "missing"


@dataclass(frozen=True)
class GnssPoseParams:
    """``receiver_latency_s`` has no default: it is the receiver's, from its manual or a
    measurement, and a silent 0 would hide a position error of speed × latency."""

    receiver_latency_s: float
    epoch_window_s: float = 0.05  # a 5-sentence burst at 115200 Bd takes ~35 ms; < period
    learn_epochs: int = 5  # sentence types of this many recent epochs are expected
    course_min_speed_mps: float = 1.0  # below it, course over ground is noise
    hdop_uere_m: float = 5.0  # per axis, standalone GPS: conservative for any fix
    yaw_rate_time_constant_s: float = 0.2
    yaw_rate_max_gap_s: float = 0.5  # longer between headings: start the rate afresh
    utc_jump_reset_s: float = 1.0  # older UTC for this long: the receiver's clock went back

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            may_be_zero = name in ("receiver_latency_s", "course_min_speed_mps")
            if not (math.isfinite(value) and (value >= 0.0 if may_be_zero else value > 0.0)):
                bound = "≥ 0" if may_be_zero else "> 0"
                raise ValueError(f"{name} must be finite and {bound}, got {value}")
        if self.learn_epochs < 1:
            raise ValueError(f"learn_epochs must be at least 1, got {self.learn_epochs}")


@dataclass(frozen=True)
class GnssPose:
    """One epoch's fix. Position is always present and finite; what the epoch lacked is
    None with its source MISSING. ``sigma_worst_m`` is the largest 1-σ in any horizontal
    direction (the GST ellipse's major axis when given): the cross-track error does not
    choose its axis."""

    measurement_time_s: float
    utc_time_of_day_s: float
    east_m: float
    north_m: float
    up_m: float
    quality: FixQuality
    satellites: int | None
    hdop: float | None
    yaw_rad: float | None
    heading_source: HeadingSource
    course_yaw_rad: float | None  # direction of travel, ENU; None when not moving
    speed_mps: float | None
    yaw_rate_rad_per_s: float | None
    sigma_east_m: float | None
    sigma_north_m: float | None
    sigma_worst_m: float | None
    sigma_source: SigmaSource


@dataclass(frozen=True)
class GnssNoFix:
    """The receiver said it has no fix (GGA quality 0 or no position, RMC status V)."""

    measurement_time_s: float
    reason: str


def _finite(value: float | None, *, positive: bool = False) -> float | None:
    """A usable number or None: events may be built by hand, not only by the parser."""
    if value is None or not math.isfinite(value) or value < 0.0 or (positive and value == 0.0):
        return None
    return value


def _kind(event: NmeaEvent) -> str | None:
    if isinstance(event, Heading):
        return event.sentence if event.sentence in ("HDT", "THS") else None
    return _KINDS.get(type(event))


@dataclass
class _Epoch:
    utc_s: float
    first_receive_s: float
    parts: dict[str, tuple[NmeaEvent, float]] = field(default_factory=dict)
    seen: set[str] = field(default_factory=set)  # kinds in its burst, also after it was out
    sealed: bool = False

    def add(self, kind: str, event: NmeaEvent, t_s: float) -> None:
        self.seen.add(kind)
        if not self.sealed:
            self.parts[kind] = (event, t_s)


class _YawRate:
    """Yaw rate from successive headings: unwrapped difference over the measurement
    interval, first-order low-pass. Restarts across a gap or a change of heading source
    (course and heading differ by the sideslip angle: the step is no rotation)."""

    def __init__(self, params: GnssPoseParams) -> None:
        self._params = params
        self.reset()

    def reset(self) -> None:
        self._last: tuple[float, float, HeadingSource] | None = None
        self._rate_rad_per_s: float | None = None

    def update(self, yaw_rad: float, source: HeadingSource, time_s: float) -> float | None:
        last, self._last = self._last, (yaw_rad, time_s, source)
        if last is None or last[2] is not source:
            self._rate_rad_per_s = None
            return None
        dt_s = time_s - last[1]
        if 0.0 <= dt_s < _MIN_RATE_INTERVAL_S:
            self._last = last
            return self._rate_rad_per_s
        if not 0.0 < dt_s <= self._params.yaw_rate_max_gap_s:
            self._rate_rad_per_s = None
            return None
        raw = wrap_angle_rad(yaw_rad - last[0]) / dt_s
        if self._rate_rad_per_s is None:
            self._rate_rad_per_s = raw
        else:
            alpha = dt_s / (self._params.yaw_rate_time_constant_s + dt_s)
            self._rate_rad_per_s += alpha * (raw - self._rate_rad_per_s)
        return self._rate_rad_per_s


class GnssPoseAssembler:
    """NMEA events with their receive times in, at most one pose (or no-fix) per epoch out.

    Feed every event with `update`; call `expire` once per control cycle so an epoch missing
    a sentence is emitted within ``epoch_window_s``. Either returns the newest output of the
    call (an older epoch superseded in the same call is only counted). Never raises on
    content: unusable input is counted in `counts`.
    """

    def __init__(self, frame: LocalFrame, params: GnssPoseParams) -> None:
        self._frame = frame
        self._params = params
        self._yaw_rate = _YawRate(params)
        self.reset()

    def reset(self) -> None:
        self._epoch: _Epoch | None = None
        self._pending: dict[str, tuple[NmeaEvent, float]] = {}
        self._recent_kinds: deque[frozenset[str]] = deque(maxlen=self._params.learn_epochs)
        self._last_receive_s = -math.inf
        self._yaw_rate.reset()
        self.counts: Counter[str] = Counter()

    def update(self, event: NmeaEvent, receive_time_s: float) -> GnssPose | GnssNoFix | None:
        t_s = receive_time_s
        if not (math.isfinite(t_s) and t_s >= self._last_receive_s):
            self.counts["bad_receive_time"] += 1
            return None
        self._last_receive_s = t_s
        out = self.expire(t_s)
        kind = _kind(event)
        if kind is None:
            self.counts["unknown_type"] += 1
            return out
        utc_s = getattr(event, "utc_time_of_day_s", None)
        if kind in _TIMED_KINDS and (utc_s is None or not 0.0 <= utc_s < _DAY_S + 1.0):
            return self._untimed_no_fix(event, t_s) or out
        if utc_s is None:
            self._add_untimed(kind, event, t_s)
        else:
            out = self._newest(out, self._add_timed(kind, event, utc_s, t_s))
        epoch = self._epoch
        if epoch is not None and not epoch.sealed and self._complete(epoch):
            out = self._newest(out, self._seal(epoch))
        return out

    def expire(self, now_s: float) -> GnssPose | GnssNoFix | None:
        """Close the open epoch if its window has passed; its output, if it has one."""
        epoch = self._epoch
        if epoch is None or epoch.sealed or not now_s - epoch.first_receive_s > self._window_s:
            return None
        return self._seal(epoch)

    @property
    def _window_s(self) -> float:
        return self._params.epoch_window_s

    def _newest(
        self, older: GnssPose | GnssNoFix | None, newer: GnssPose | GnssNoFix | None
    ) -> GnssPose | GnssNoFix | None:
        if newer is None:
            return older
        if older is not None:
            self.counts["superseded"] += 1
        return newer

    def _complete(self, epoch: _Epoch) -> bool:
        expected = frozenset[str]().union(*self._recent_kinds)
        return bool(expected) and "GGA" in epoch.parts and expected.issubset(epoch.parts)

    def _add_untimed(self, kind: str, event: NmeaEvent, t_s: float) -> None:
        epoch = self._epoch
        if epoch is not None and t_s - epoch.first_receive_s <= self._window_s:
            if epoch.sealed:
                self.counts["after_emit"] += 1  # in its burst, but the epoch is already out
            epoch.add(kind, event, t_s)
            return
        self._pending[kind] = (event, t_s)

    def _add_timed(
        self, kind: str, event: NmeaEvent, utc_s: float, t_s: float
    ) -> GnssPose | GnssNoFix | None:
        epoch = self._epoch
        step_s = 0.0 if epoch is None else _utc_step_s(epoch.utc_s, utc_s)
        if epoch is not None and abs(step_s) < 5e-4:
            if epoch.sealed:
                self.counts["late"] += 1
            epoch.add(kind, event, t_s)
            return None
        if epoch is not None and step_s < 0.0:
            if t_s - epoch.first_receive_s <= self._params.utc_jump_reset_s:
                self.counts["late"] += 1
                return None
            self.counts["utc_jump"] += 1
            self._recent_kinds.clear()
            self._yaw_rate.reset()
        out = None
        if epoch is not None:
            if not epoch.sealed:
                out = self._seal(epoch)
            self._recent_kinds.append(frozenset(epoch.seen))
        self._epoch = _Epoch(utc_s, t_s)
        self._epoch.add(kind, event, t_s)
        for pending_kind, (pending, pending_t_s) in self._pending.items():
            if t_s - pending_t_s <= self._window_s:
                self._epoch.add(pending_kind, pending, pending_t_s)
        self._pending.clear()
        return out

    def _seal(self, epoch: _Epoch) -> GnssPose | GnssNoFix | None:
        epoch.sealed = True
        out = self._build(epoch)
        if out is None:
            self.counts["no_gga"] += 1
        return out

    def _untimed_no_fix(self, event: NmeaEvent, t_s: float) -> GnssNoFix | None:
        """A GGA or RMC without a time cannot join an epoch; if it says "no fix", that
        needs no epoch to be true."""
        reason = None
        if isinstance(event, GgaFix):
            reason = _gga_no_fix_reason(event)
        elif isinstance(event, RmcFix) and not event.valid:
            reason = "RMC void"
        if reason is None:
            self.counts["no_time"] += 1
            return None
        return GnssNoFix(t_s - self._params.receiver_latency_s, reason)

    def _build(self, epoch: _Epoch) -> GnssPose | GnssNoFix | None:
        gga_part = epoch.parts.get("GGA")
        rmc_part = epoch.parts.get("RMC")
        rmc = rmc_part[0] if rmc_part is not None else None
        if gga_part is None:
            if rmc_part is not None and isinstance(rmc, RmcFix) and not rmc.valid:
                return GnssNoFix(rmc_part[1] - self._params.receiver_latency_s, "RMC void")
            return None
        gga, receive_s = gga_part
        time_s = receive_s - self._params.receiver_latency_s
        if not isinstance(gga, GgaFix):
            return None
        reason = _gga_no_fix_reason(gga)
        if reason is None and isinstance(rmc, RmcFix) and not rmc.valid:
            reason = "RMC void"
        if reason is not None or gga.lat_deg is None or gga.lon_deg is None or not gga.quality:
            return GnssNoFix(time_s, reason or "GGA without position")
        # LocalFrame is on the WGS 84 ellipsoid; GGA's altitude is above the geoid.
        altitude_m = self._frame.origin_alt_m
        msl_m, geoid_m = _finite_signed(gga.altitude_m), _finite_signed(gga.geoid_separation_m)
        if msl_m is not None and abs(msl_m) < _PLAUSIBLE_ALTITUDE_M:
            separation_m = geoid_m if geoid_m is not None and abs(geoid_m) < 200.0 else 0.0
            altitude_m = msl_m + separation_m
        enu = self._frame.to_local(gga.lat_deg, gga.lon_deg, altitude_m)
        if not all(math.isfinite(v) for v in enu):
            return GnssNoFix(time_s, "position outside the local frame")
        # True north at the antenna is turned by the meridians' convergence against ENU north.
        convergence_rad = wrap_angle_rad(
            math.radians(gga.lon_deg - self._frame.origin_lon_deg)
        ) * math.sin(math.radians(gga.lat_deg))
        speed_mps, course_yaw_rad = self._velocity(epoch, convergence_rad)
        yaw_rad, source = self._heading(epoch, convergence_rad)
        if yaw_rad is None and course_yaw_rad is not None:
            yaw_rad, source = course_yaw_rad, HeadingSource.COURSE
        yaw_rate = None if yaw_rad is None else self._yaw_rate.update(yaw_rad, source, time_s)
        hdop = _finite(gga.hdop)
        sigma_e, sigma_n, sigma_worst, sigma_source = self._sigma(epoch, hdop)
        return GnssPose(
            measurement_time_s=time_s,
            utc_time_of_day_s=epoch.utc_s,
            east_m=enu[0],
            north_m=enu[1],
            up_m=enu[2],
            quality=gga.quality,
            satellites=gga.satellites,
            hdop=hdop,
            yaw_rad=yaw_rad,
            heading_source=source,
            course_yaw_rad=course_yaw_rad,
            speed_mps=speed_mps,
            yaw_rate_rad_per_s=yaw_rate,
            sigma_east_m=sigma_e,
            sigma_north_m=sigma_n,
            sigma_worst_m=sigma_worst,
            sigma_source=sigma_source,
        )

    def _velocity(self, epoch: _Epoch, convergence_rad: float) -> tuple[float | None, float | None]:
        """(speed, ENU direction of travel); VTG first (km/h has more digits than knots)."""
        for kind in ("VTG", "RMC"):
            part = epoch.parts.get(kind)
            velocity = part[0] if part is not None else None
            if not isinstance(velocity, VtgVelocity | RmcFix) or not velocity.valid:
                continue
            speed_mps = _finite(velocity.speed_mps)
            if speed_mps is None or speed_mps > _PLAUSIBLE_SPEED_MPS:
                continue
            course_rad = _finite_signed(velocity.course_rad)
            if course_rad is None or speed_mps < self._params.course_min_speed_mps:
                return speed_mps, None
            return speed_mps, _enu_yaw(course_rad, convergence_rad)
        return None, None

    @staticmethod
    def _heading(epoch: _Epoch, convergence_rad: float) -> tuple[float | None, HeadingSource]:
        """The latest valid HDT or THS of the epoch."""
        latest: tuple[float, float] | None = None
        for kind in ("HDT", "THS"):
            part = epoch.parts.get(kind)
            if part is None or not isinstance(part[0], Heading) or not part[0].valid:
                continue
            heading_rad = _finite_signed(part[0].heading_rad)
            if heading_rad is not None and (latest is None or part[1] >= latest[1]):
                latest = (heading_rad, part[1])
        if latest is None:
            return None, HeadingSource.MISSING
        return _enu_yaw(latest[0], convergence_rad), HeadingSource.TRUE_HEADING

    def _sigma(
        self, epoch: _Epoch, hdop: float | None
    ) -> tuple[float | None, float | None, float | None, SigmaSource]:
        """GST's σ when it gives both axes (a σ of 0 is no estimate); else HDOP × UERE on
        each axis, which overstates an RTK fix's error: deny by default, ask for GST."""
        part = epoch.parts.get("GST")
        gst = part[0] if part is not None else None
        if isinstance(gst, GstError):
            east = _finite(gst.sigma_lon_m, positive=True)
            north = _finite(gst.sigma_lat_m, positive=True)
            if east is not None and north is not None:
                major = _finite(gst.ellipse_major_m, positive=True) or 0.0
                return east, north, max(east, north, major), SigmaSource.GST
        sigma_m = (hdop or 0.0) * self._params.hdop_uere_m
        if 0.0 < sigma_m < math.inf:
            return sigma_m, sigma_m, sigma_m, SigmaSource.HDOP
        return None, None, None, SigmaSource.MISSING


def _finite_signed(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _enu_yaw(true_direction_rad: float, convergence_rad: float) -> float:
    """Clockwise from true north at the antenna to counter-clockwise from ENU east."""
    return wrap_angle_rad(math.pi / 2.0 - true_direction_rad + convergence_rad)


def _utc_step_s(from_utc_s: float, to_utc_s: float) -> float:
    """Signed seconds from one time of day to another, the short way round midnight."""
    return (to_utc_s - from_utc_s + _DAY_S / 2.0) % _DAY_S - _DAY_S / 2.0


def _gga_no_fix_reason(gga: GgaFix) -> str | None:
    if gga.quality is None or gga.quality is FixQuality.INVALID:
        return "GGA quality 0"
    lat, lon = _finite_signed(gga.lat_deg), _finite_signed(gga.lon_deg)
    if lat is None or lon is None or abs(lat) > 90.0 or abs(lon) > 180.0:
        return "GGA without position"
    return None
