"""A simulated GNSS/INS receiver: NMEA 0183 on a pty, from the simulated vehicle's pose.

`NmeaSynth` is the receiver's behaviour and nothing else (sans-I/O, time as an argument): given
the true pose at ``now_s`` it decides whether an epoch is due and returns the bytes of that
epoch as the writes a serial port would carry, with everything a real receiver does to a
tracker: white position and heading noise, the 0.3 m jumps of Stanley et al.'s threshold
switching between LGPR and GPS/INS, dropouts, scheduled quality changes (RTK fixed -> GPS ->
no fix, with GGA's quality field and GST's sigma following), lines with a flipped bit, and lines
cut across writes or glued into one. Every random choice comes from the seed, each concern
from its own stream, so turning corruption on does not change the noise a test sees.
`GnssTwin` is the thin writer: the synth's writes go to the master side of a `PtyLink`, and the
client opens the slave path exactly as it opens ``/dev/serial/by-id/...`` on the vehicle.

Schedules (jumps, dropouts, quality changes) count seconds from the first epoch, which is the
first `update`; UTC in the sentences is `utc_start` plus the epoch's place on the rate's grid
(a real receiver's epochs fall on round times too), and the position is the pose given with it.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import numpy as np

from appliance.localization.local_frame import LocalFrame
from drivers.gnss.nmea import nmea_checksum
from drivers.gnss.sentences import KMH_MPS, KNOT_MPS, FixQuality
from drivers.ptylink import PtyLink

SUPPORTED_SENTENCES: Final = frozenset({"GGA", "RMC", "VTG", "HDT", "THS", "GST"})
# NMEA 0183: at most 82 characters from "$" to the line end inclusive, so 80 before CRLF.
MAX_LINE_CHARS: Final = 80
# Below this speed a course over ground means nothing; receivers leave the field empty.
MIN_COURSE_SPEED_MPS: Final = 0.01

_RMC_MODE: Final = {
    FixQuality.INVALID: "N",
    FixQuality.GPS: "A",
    FixQuality.DGPS: "D",
    FixQuality.PPS: "A",
    FixQuality.RTK_FIXED: "R",
    FixQuality.RTK_FLOAT: "F",
    FixQuality.DEAD_RECKONING: "E",
    FixQuality.MANUAL: "M",
    FixQuality.SIMULATION: "S",
}
_DIFFERENTIAL: Final = frozenset({FixQuality.DGPS, FixQuality.RTK_FIXED, FixQuality.RTK_FLOAT})
_NOISE, _JUMP, _DROPOUT, _WIRE = range(4)  # the seed's independent streams


@dataclass(frozen=True)
class QualityChange:
    """From ``at_s`` (seconds since the first epoch) the receiver reports this solution."""

    at_s: float
    quality: FixQuality
    sigma_m: float  # 1-sigma white noise per horizontal axis, and what GST reports
    satellites: int
    hdop: float


@dataclass(frozen=True)
class Dropout:
    """No output at all from ``at_s`` for ``duration_s`` (antenna shadowed, receiver reset)."""

    at_s: float
    duration_s: float


@dataclass(frozen=True)
class GnssTwinParams:
    """What the simulated receiver sends. The defaults are a clean RTK receiver at 10 Hz:
    set ``jump_m=0.3`` for the paper's LGPR/GPS switching, and the fault fields to taste."""

    origin_lat_deg: float = 42.4591
    origin_lon_deg: float = -71.2674
    origin_alt_m: float = 100.0
    rate_hz: float = 10.0
    sentences: tuple[str, ...] = ("GGA", "RMC", "VTG", "HDT", "GST")
    talker: str = "GN"
    utc_start: dt.datetime = dt.datetime(2024, 6, 1, 12, 0, 0, tzinfo=dt.UTC)
    # The solution at the first epoch; `quality_changes` replace it at their times.
    quality: FixQuality = FixQuality.RTK_FIXED
    position_noise_m: float = 0.05
    satellites: int = 16
    hdop: float = 0.7
    quality_changes: tuple[QualityChange, ...] = ()
    heading_noise_rad: float = math.radians(0.1)
    differential_age_s: float = 1.0
    # Threshold switching: every jump_period_s the offset flips between none and jump_m in
    # a direction drawn anew each time it switches on.
    jump_m: float = 0.0
    jump_period_s: float = 20.0
    dropouts: tuple[Dropout, ...] = ()
    random_dropouts_per_s: float = 0.0  # a Poisson process of dropouts of this length
    random_dropout_s: float = 1.0
    corrupt_fraction: float = 0.0  # lines sent with one bit flipped (the checksum fails)
    split_fraction: float = 0.0  # lines cut into two writes at a random byte
    merge_fraction: float = 0.0  # lines written in one write with the next line
    minute_decimals: int = 7  # of the minutes in ddmm.mmmmmmm (1e-7 min = 0.19 mm)

    def __post_init__(self) -> None:
        LocalFrame(self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m)  # checks it
        problems: list[str] = []
        if not 1.0 <= self.rate_hz <= 20.0:
            problems.append(f"rate_hz {self.rate_hz} outside 1..20")
        unknown = set(self.sentences) - SUPPORTED_SENTENCES
        if not self.sentences or unknown or len(set(self.sentences)) != len(self.sentences):
            problems.append(
                f"sentences {self.sentences}: each once, of {sorted(SUPPORTED_SENTENCES)}"
            )
        if len(self.talker) != 2 or not self.talker.isalnum() or not self.talker.isupper():
            problems.append(f"talker {self.talker!r} is not two capitals (GN, GP, ...)")
        if self.utc_start.tzinfo is None:
            problems.append("utc_start needs a time zone (UTC)")
        for name in ("corrupt_fraction", "split_fraction", "merge_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                problems.append(f"{name} outside 0..1")
        for name in ("position_noise_m", "heading_noise_rad", "jump_m", "random_dropouts_per_s"):
            if not getattr(self, name) >= 0.0:
                problems.append(f"{name} is negative")
        if self.jump_period_s <= 0.0 or self.random_dropout_s <= 0.0:
            problems.append("jump_period_s and random_dropout_s must be positive")
        if not 4 <= self.minute_decimals <= 8:
            problems.append("minute_decimals outside 4..8")
        times = [change.at_s for change in self.quality_changes]
        if times != sorted(times) or any(c.sigma_m < 0 or c.hdop < 0 for c in self.quality_changes):
            problems.append("quality_changes must be in time order, with sigma and HDOP >= 0")
        if problems:
            raise ValueError("; ".join(problems))


@dataclass(frozen=True)
class NmeaEpoch:
    """One epoch: what went onto the wire and the truth behind it (for tests and benches)."""

    t_s: float  # seconds since the first epoch, on the rate's grid
    utc: dt.datetime
    writes: tuple[bytes, ...]  # each one write to the port, in order; () in a dropout
    lines: int
    corrupted: int  # lines among them with a flipped bit
    dropout: bool
    quality: FixQuality
    sigma_m: float
    offset_east_m: float  # the jump offset added to the pose (noise not included)
    offset_north_m: float


def sentence_line(body: str) -> bytes:
    """``$`` + body + ``*hh`` + CRLF."""
    return f"${body}*{nmea_checksum(body):02X}\r\n".encode("ascii")


def degrees_minutes(value_deg: float, *, latitude: bool, decimals: int) -> tuple[str, str]:
    """Signed decimal degrees as (``ddmm.mmmm`` or ``dddmm.mmmm``, hemisphere), rounded in
    integer units so that minutes never print as 60."""
    scale = 10**decimals
    units = round(abs(value_deg) * 60.0 * scale)
    whole_deg, rest = divmod(units, 60 * scale)
    minutes, fraction = divmod(rest, scale)
    width = 2 if latitude else 3
    hemisphere = ("N" if value_deg >= 0 else "S") if latitude else ("E" if value_deg >= 0 else "W")
    return f"{whole_deg:0{width}d}{minutes:02d}.{fraction:0{decimals}d}", hemisphere


def nmea_time(utc: dt.datetime) -> str:
    return f"{utc:%H%M%S}.{utc.microsecond // 10_000:02d}"


def true_heading_deg(yaw_rad: float) -> float:
    """ENU yaw (counter-clockwise from east) as a true heading (clockwise from north)."""
    return (90.0 - math.degrees(yaw_rad)) % 360.0


class NmeaSynth:
    """The receiver's behaviour: pose in, an epoch's writes out, at most one per update."""

    def __init__(self, params: GnssTwinParams = GnssTwinParams(), *, seed: int = 0) -> None:
        self.params = params
        self.seed = seed
        self.frame = LocalFrame(params.origin_lat_deg, params.origin_lon_deg, params.origin_alt_m)
        self.reset()

    def reset(self) -> None:
        self._start_s: float | None = None
        self._next_index = 0
        self._rng = {k: np.random.default_rng([self.seed, k]) for k in (_NOISE, _DROPOUT, _WIRE)}
        self._next_random_dropout_s = self._draw_random_dropout(0.0)
        self.epochs = 0
        self.lines = 0
        self.corrupted_lines = 0
        self.dropped_epochs = 0
        # Set from outside (the bench: the antenna under a roof) and cleared the same way;
        # an epoch while shadowed is a dropout like a scheduled one.
        self.shadowed = False

    def update(
        self, now_s: float, east_m: float, north_m: float, yaw_rad: float, speed_mps: float
    ) -> NmeaEpoch | None:
        """The epoch due at ``now_s`` for the true pose then, or None between epochs.

        ``yaw_rad`` is the ENU yaw (counter-clockwise from east, as the simulated vehicle's
        state has it); ``speed_mps`` is signed (negative: reversing, the course turns round).
        A caller late by several periods gets one epoch, not a burst.
        """
        p = self.params
        if self._start_s is None:
            self._start_s = now_s
        elapsed_s = now_s - self._start_s
        if elapsed_s * p.rate_hz < self._next_index - 1e-6:
            return None
        index = max(self._next_index, math.floor(elapsed_s * p.rate_hz + 1e-6))
        self._next_index = index + 1
        t_s = index / p.rate_hz
        utc = p.utc_start + dt.timedelta(microseconds=round(t_s * 100) * 10_000)
        quality, sigma_m, satellites, hdop = self.solution(t_s)
        offset_east_m, offset_north_m = self.jump_offset_m(t_s)
        truth = (quality, sigma_m, offset_east_m, offset_north_m)
        self.epochs += 1
        if self.shadowed or self.in_dropout(t_s):
            self.dropped_epochs += 1
            return NmeaEpoch(t_s, utc, (), 0, 0, True, *truth)
        noise = self._rng[_NOISE].normal(0.0, 1.0, 3)
        east = east_m + offset_east_m + sigma_m * float(noise[0])
        north = north_m + offset_north_m + sigma_m * float(noise[1])
        yaw = yaw_rad + p.heading_noise_rad * float(noise[2])
        lat_deg, lon_deg, alt_m = self.frame.to_geodetic(east, north, 0.0)
        fixed = quality is not FixQuality.INVALID
        bodies = []
        for kind in p.sentences:
            if kind == "GGA":
                bodies.append(self._gga(utc, lat_deg, lon_deg, alt_m, quality, satellites, hdop))
            elif kind == "RMC":
                bodies.append(self._rmc(utc, lat_deg, lon_deg, yaw, speed_mps, quality))
            elif kind == "VTG":
                bodies.append(self._vtg(yaw, speed_mps, quality))
            elif kind in ("HDT", "THS"):
                bodies.append(self._heading(kind, yaw if fixed else None))
            else:
                bodies.append(self._gst(utc, sigma_m if fixed else None))
        lines = [sentence_line(body) for body in bodies]
        corrupted = self._corrupt(lines)
        self.lines += len(lines)
        self.corrupted_lines += corrupted
        return NmeaEpoch(t_s, utc, self._writes(lines), len(lines), corrupted, False, *truth)

    # ---- the schedules (pure functions of time since the first epoch) ---------------------
    def solution(self, t_s: float) -> tuple[FixQuality, float, int, float]:
        """(quality, sigma, satellites, HDOP) in force at ``t_s``."""
        p = self.params
        current = (p.quality, p.position_noise_m, p.satellites, p.hdop)
        for change in p.quality_changes:
            if change.at_s <= t_s + 1e-9:
                current = (change.quality, change.sigma_m, change.satellites, change.hdop)
        return current

    def jump_offset_m(self, t_s: float) -> tuple[float, float]:
        """Zero in even jump periods, ``jump_m`` in a per-period seeded direction in odd ones."""
        p = self.params
        period = math.floor(t_s / p.jump_period_s + 1e-9)
        if p.jump_m == 0.0 or period % 2 == 0:
            return 0.0, 0.0
        angle_rad = float(np.random.default_rng([self.seed, _JUMP, period]).uniform(0, math.tau))
        return p.jump_m * math.cos(angle_rad), p.jump_m * math.sin(angle_rad)

    def in_dropout(self, t_s: float) -> bool:
        if any(d.at_s <= t_s < d.at_s + d.duration_s for d in self.params.dropouts):
            return True
        if self.params.random_dropouts_per_s <= 0.0:
            return False
        end_s = self._next_random_dropout_s + self.params.random_dropout_s
        while t_s >= end_s:  # that one is over: schedule the next
            self._next_random_dropout_s = self._draw_random_dropout(end_s)
            end_s = self._next_random_dropout_s + self.params.random_dropout_s
        return t_s >= self._next_random_dropout_s

    def _draw_random_dropout(self, after_s: float) -> float:
        rate = self.params.random_dropouts_per_s
        return (
            math.inf if rate <= 0.0 else after_s + float(self._rng[_DROPOUT].exponential(1 / rate))
        )

    # ---- the sentences ---------------------------------------------------------------------
    def _gga(
        self,
        utc: dt.datetime,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        quality: FixQuality,
        satellites: int,
        hdop: float,
    ) -> str:
        """GGA with as many minute decimals as fit in 80 characters (a receiver configured for
        more would overrun the standard's line length; fewer lose precision, not the line)."""
        head = f"{self.params.talker}GGA,{nmea_time(utc)}"
        if quality is FixQuality.INVALID:
            return f"{head},,,,,0,{satellites:02d},{hdop:.1f},,,,,,"
        age = f"{self.params.differential_age_s:.1f}" if quality in _DIFFERENTIAL else ""
        tail = f"{int(quality)},{satellites:02d},{hdop:.1f},{alt_m:.2f},M,0.0,M,{age},"
        return self._fit(head + ",{}," + tail, lat_deg, lon_deg)

    def _fit(self, template: str, lat_deg: float, lon_deg: float) -> str:
        """``template`` with the position in place of ``{}``, with the most minute decimals
        (up to `minute_decimals`) that keep the line within the standard's length."""
        for decimals in range(self.params.minute_decimals, 3, -1):
            lat, ns = degrees_minutes(lat_deg, latitude=True, decimals=decimals)
            lon, ew = degrees_minutes(lon_deg, latitude=False, decimals=decimals)
            body = template.format(f"{lat},{ns},{lon},{ew}")
            if len(body) + 4 <= MAX_LINE_CHARS:  # + "$" and "*hh"
                break
        return body

    def _rmc(
        self,
        utc: dt.datetime,
        lat_deg: float,
        lon_deg: float,
        yaw_rad: float,
        speed_mps: float,
        quality: FixQuality,
    ) -> str:
        head = f"{self.params.talker}RMC,{nmea_time(utc)}"
        date, mode = f"{utc:%d%m%y}", _RMC_MODE[quality]
        if quality is FixQuality.INVALID:
            return f"{head},V,,,,,,,{date},,,{mode}"
        speed = f"{abs(speed_mps) / KNOT_MPS:.3f}"
        tail = f"{speed},{_course(yaw_rad, speed_mps)},{date},,,{mode}"
        return self._fit(head + ",A,{}," + tail, lat_deg, lon_deg)

    def _vtg(self, yaw_rad: float, speed_mps: float, quality: FixQuality) -> str:
        head, mode = f"{self.params.talker}VTG", _RMC_MODE[quality]
        if quality is FixQuality.INVALID:
            return f"{head},,T,,M,,N,,K,{mode}"
        knots, kmh = abs(speed_mps) / KNOT_MPS, abs(speed_mps) / KMH_MPS
        return f"{head},{_course(yaw_rad, speed_mps)},T,,M,{knots:.3f},N,{kmh:.3f},K,{mode}"

    def _heading(self, kind: str, yaw_rad: float | None) -> str:
        value = "" if yaw_rad is None else f"{true_heading_deg(yaw_rad):.3f}"
        if kind == "HDT":
            return f"{self.params.talker}HDT,{value},T"
        return f"{self.params.talker}THS,{value},{'V' if yaw_rad is None else 'A'}"

    def _gst(self, utc: dt.datetime, sigma_m: float | None) -> str:
        head = f"{self.params.talker}GST,{nmea_time(utc)}"
        if sigma_m is None:
            return f"{head},,,,,,,"
        s = sigma_m
        return f"{head},{s:.3f},{s:.3f},{s:.3f},0.0,{s:.3f},{s:.3f},{2 * s:.3f}"

    # ---- the wire ----------------------------------------------------------------------------
    def _corrupt(self, lines: list[bytes]) -> int:
        """Flip the lowest bit of one byte between ``$`` and ``*`` in a fraction of the lines.

        That bit keeps every character of a sentence body printable and never makes a
        ``$``, ``!``, ``*`` or line end (those would be counted as other faults), and any
        flip in the body changes the XOR checksum: each such line is a checksum reject.
        """
        fraction, rng, corrupted = self.params.corrupt_fraction, self._rng[_WIRE], 0
        for i, line in enumerate(lines):
            if fraction > 0.0 and rng.random() < fraction:
                position = int(rng.integers(1, line.index(b"*")))
                damaged = bytearray(line)
                damaged[position] ^= 0x01
                lines[i] = bytes(damaged)
                corrupted += 1
        return corrupted

    def _writes(self, lines: list[bytes]) -> tuple[bytes, ...]:
        """The epoch's lines as writes: some cut at a random byte, some glued to the next."""
        p, rng = self.params, self._rng[_WIRE]
        writes: list[bytes] = []
        pending = b""
        for line in lines:
            if p.split_fraction > 0.0 and rng.random() < p.split_fraction:
                cut = int(rng.integers(1, len(line)))
                writes.append(pending + line[:cut])
                pending, line = b"", line[cut:]
            pending += line
            if not (p.merge_fraction > 0.0 and rng.random() < p.merge_fraction):
                writes.append(pending)
                pending = b""
        if pending:
            writes.append(pending)
        return tuple(writes)


def _course(yaw_rad: float, speed_mps: float) -> str:
    """Course over ground, empty at a standstill; reversing moves against the heading."""
    if abs(speed_mps) < MIN_COURSE_SPEED_MPS:
        return ""
    course = true_heading_deg(yaw_rad) + (180.0 if speed_mps < 0 else 0.0)
    return f"{course % 360.0:.2f}"


class GnssTwin:
    """The simulated receiver behind a pty: `update` with the true pose, a client reads it."""

    def __init__(
        self, link_path: str, params: GnssTwinParams = GnssTwinParams(), *, seed: int = 0
    ) -> None:
        self.synth = NmeaSynth(params, seed=seed)
        self.link = PtyLink(link_path)

    @property
    def port_path(self) -> str:
        """The stable path a client opens (a symlink to the current pty slave)."""
        return self.link.link_path

    def update(
        self, now_s: float, east_m: float, north_m: float, yaw_rad: float, speed_mps: float
    ) -> NmeaEpoch | None:
        """Write the epoch due now, if any (see `NmeaSynth.update`); each write separately."""
        epoch = self.synth.update(now_s, east_m, north_m, yaw_rad, speed_mps)
        if epoch is not None:
            for data in epoch.writes:
                self.link.write(data)
        return epoch

    async def run(
        self,
        pose: Callable[[float], tuple[float, float, float, float]],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """Send at the configured rate in real time until cancelled; ``pose(now_s)`` gives
        (east_m, north_m, yaw_rad, speed_mps)."""
        period_s = 1.0 / self.synth.params.rate_hz
        next_s = clock()
        while True:
            now_s = clock()
            self.update(now_s, *pose(now_s))
            next_s = max(next_s + period_s, now_s)
            await asyncio.sleep(max(0.0, next_s - clock()))

    def inject_noise(self, data: bytes) -> None:
        """Raw bytes onto the wire (garbage between sentences)."""
        self.link.write(data)

    def unplug(self) -> None:
        """Pull the cable: the client sees EOF/EIO, the path disappears."""
        self.link.unplug()

    def replug(self) -> None:
        """A new pty behind the same path; the epochs go on where they were."""
        self.link.plug()

    def close(self) -> None:
        self.link.unplug()
