"""The decoded scan: raw fields as sent, plus SI views (metres, radians).

The device measures angles in 1/10000 degree and distances as ``raw * scale + offset``
millimetres, raw 0 meaning "no echo"; this module converts once, at the edge, so everything
downstream reads `Scan.ranges_m` and `Scan.angles_rad` (sensor frame: start + i * step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from functools import cached_property

import numpy as np
import numpy.typing as npt

from drivers.lms111.values import RawArray

ANGLE_UNITS_PER_DEG = 10_000
_RAD_PER_ANGLE_UNIT = math.pi / 180.0 / ANGLE_UNITS_PER_DEG

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Channel:
    """One output channel as sent: raw integer data plus how to scale and place it."""

    name: str
    scale_factor: float
    scale_offset: float
    start_angle_10000th_deg: int
    angular_step_10000th_deg: int
    data: RawArray  # uint16 or uint8, read-only

    @property
    def start_angle_rad(self) -> float:
        return self.start_angle_10000th_deg * _RAD_PER_ANGLE_UNIT

    @property
    def angular_step_rad(self) -> float:
        return self.angular_step_10000th_deg * _RAD_PER_ANGLE_UNIT

    def values(self) -> FloatArray:
        """``raw * scale + offset`` (millimetres for DIST, digits for RSSI)."""
        scaled: FloatArray = self.data * np.float64(self.scale_factor) + self.scale_offset
        return scaled

    def angles_rad(self) -> FloatArray:
        """Sensor-frame angle of each value: start + i * step."""
        steps = np.arange(len(self.data), dtype=np.float64)
        angles: FloatArray = self.start_angle_rad + steps * self.angular_step_rad
        return angles


@dataclass(frozen=True)
class Encoder:
    position_ticks: int
    speed_ticks_per_mm: int


@dataclass(frozen=True)
class Position:
    """The optional position block, in whatever frame and unit was configured in SOPAS."""

    x: float
    y: float
    z: float
    rotation_x: float
    rotation_y: float
    rotation_z: float
    rotation_type: int  # 0 none, 1 pitch, 2 roll, 3 free
    transmit_device_name: int


@dataclass(frozen=True)
class ScanTimestamp:
    """The device's calendar clock (not synchronised to the host)."""

    year: int
    month: int
    day: int
    hour: int
    minute: int
    second: int
    microsecond: int


@dataclass(frozen=True)
class ScanEvent:
    event_type: str  # "FDIN": fast digital input
    encoder_position_ticks: int
    event_time_us: int
    angular_position_10000th_deg: int


@dataclass(frozen=True, eq=False)
class Scan:
    """One decoded ``LMDscandata`` telegram.

    Raw fields mirror the telegram (so the twin can encode one exactly); the SI views
    (`ranges_m`, `angles_rad`, `intensities`) are computed once on first use.
    `host_receive_time_s` is whatever the caller stamps: the core has no clock.
    """

    channels_16bit: tuple[Channel, ...] = ()
    channels_8bit: tuple[Channel, ...] = ()
    version: int = 1
    device_number: int = 0
    serial_number: int = 0
    device_status: int = 0  # the two status bytes, first one high
    telegram_counter: int = 0
    scan_counter: int = 0
    device_time_us: int = 0  # raw 32-bit time since start-up at the scan's zero index
    transmit_time_us: int = 0
    input_status: int = 0
    output_status: int = 0
    reserved: int = 0
    scan_frequency_100th_hz: int = 0
    measurement_frequency_100hz: int = 0
    encoders: tuple[Encoder, ...] = ()
    position: Position | None = None
    device_name: str | None = None
    comment: str | None = None
    timestamp: ScanTimestamp | None = None
    event: ScanEvent | None = None
    host_receive_time_s: float | None = None

    def __getstate__(self) -> dict[str, object]:
        """Only the fields: a scan handed to another process (the recorder) carries its
        raw channels, not the metres and radians computed from them (5x the bytes)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @property
    def scan_frequency_hz(self) -> float:
        return self.scan_frequency_100th_hz / 100.0

    @property
    def measurement_frequency_hz(self) -> float:
        return self.measurement_frequency_100hz * 100.0

    def channel(self, name: str) -> Channel | None:
        """The first channel with this content name, 16-bit channels first."""
        for channel in self.channels_16bit + self.channels_8bit:
            if channel.name == name:
                return channel
        return None

    @cached_property
    def channels(self) -> dict[str, Channel]:
        """Every channel by name (the first one wins on duplicates)."""
        by_name: dict[str, Channel] = {}
        for channel in self.channels_16bit + self.channels_8bit:
            by_name.setdefault(channel.name, channel)
        return by_name

    @property
    def _geometry_channel(self) -> Channel | None:
        if "DIST1" in self.channels:
            return self.channels["DIST1"]
        all_channels = self.channels_16bit + self.channels_8bit
        return all_channels[0] if all_channels else None

    @property
    def angular_step_rad(self) -> float:
        geometry = self._geometry_channel
        return geometry.angular_step_rad if geometry else 0.0

    @cached_property
    def ranges_m(self) -> FloatArray:
        """DIST1 in metres; 0.0 where the scanner saw no echo (raw 0). Empty without DIST1."""
        dist = self.channels.get("DIST1")
        if dist is None:
            ranges = np.zeros(0)
        else:
            ranges = dist.values() * 1e-3
            ranges[dist.data == 0] = 0.0
        ranges.flags.writeable = False
        return ranges

    @cached_property
    def angles_rad(self) -> FloatArray:
        geometry = self._geometry_channel
        angles = geometry.angles_rad() if geometry else np.zeros(0)
        angles.flags.writeable = False
        return angles

    @cached_property
    def intensities(self) -> FloatArray | None:
        """RSSI1, scaled (digits on an LMS111), or None when the scanner sends none."""
        rssi = self.channels.get("RSSI1")
        if rssi is None:
            return None
        values = rssi.values()
        values.flags.writeable = False
        return values

    def with_host_time(self, host_receive_time_s: float) -> Scan:
        return replace(self, host_receive_time_s=host_receive_time_s)


def scan_from_ranges(
    ranges_m: npt.ArrayLike,
    *,
    start_angle_deg: float = -45.0,
    angular_step_deg: float = 0.5,
    intensities: npt.ArrayLike | None = None,
    scan_frequency_hz: float = 50.0,
) -> Scan:
    """A `Scan` as an LMS111 would send it, from ranges in metres (for the twin).

    Non-finite or non-positive ranges become raw 0 ("no echo"); the scale factor is 1 mm per
    digit, or 2 when a range exceeds what a uint16 of millimetres holds (65.535 m). Set the
    counters and times with `dataclasses.replace`.
    """
    ranges = np.asarray(ranges_m, dtype=np.float64)
    valid = np.isfinite(ranges) & (ranges > 0)
    longest_mm = float(ranges[valid].max()) * 1e3 if valid.any() else 0.0
    scale = 2.0 if longest_mm > 0xFFFF else 1.0
    raw = np.zeros(len(ranges), dtype=np.uint16)
    raw[valid] = np.clip(np.rint(ranges[valid] * 1e3 / scale), 1, 0xFFFF)
    start = round(start_angle_deg * ANGLE_UNITS_PER_DEG)
    step = round(angular_step_deg * ANGLE_UNITS_PER_DEG)
    channels = [Channel("DIST1", scale, 0.0, start, step, raw)]
    if intensities is not None:
        rssi = np.asarray(intensities, dtype=np.float64)
        rssi = np.clip(np.rint(np.nan_to_num(rssi, nan=0.0)), 0, 0xFFFF)
        channels.append(Channel("RSSI1", 1.0, 0.0, start, step, rssi.astype(np.uint16)))
    for channel in channels:
        channel.data.flags.writeable = False
    return Scan(
        channels_16bit=tuple(channels),
        scan_frequency_100th_hz=round(scan_frequency_hz * 100),
    )
