"""Typed answers: what the client reads from a `Reply`, and what the twin sends back.

Formats (CoLa-A examples from SICK's listings and real LMS1xx captures):

* ``sAN SetAccessMode 1`` (0 = refused); CoLa-B one byte.
* ``sRA LMPscancfg 1388 1 1388 FFF92230 225510``: frequency 1/100 Hz (uint32), sector count
  (uint16), then per sector resolution (uint32), start and stop (int32), 1/10000°.
* ``sAN mLMPsetscancfg 0 1388 1 1388 FFF92230 225510``: status (uint8: 0 ok, 1 frequency,
  2 resolution, 3 frequency and resolution, 4 scan area, 5 other), then as above.
* ``sRA LMPoutputRange 1 1388 FFF92230 225510``: sectors, resolution, start, stop.
* ``sRA STlms 7 0 8 00:34:19 A 01.01.1970 0 0 0``: state (uint16, 7 = measuring), temperature
  out of range (uint8), device time and date (flexible strings), LED 1..3 (uint16 in CoLa-B,
  per Wireshark; newer firmware appends reserved bytes, ignored).
* ``sRA SCdevicestate 1`` (0 busy, 1 ready, 2 error); ``sRA DeviceIdent 10 LMS10x_FieldEval 10
  V1.36-21.10.2010`` (two flexible strings); ``sRA FirmwareVersion``, ``sRA LocationName``
  (one flexible string each).
* method answers with one status byte: ``sAN LMCstartmeas 0``, ``sAN Run 1``.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

from drivers.lms111.cola import Command, CommandType, Reply
from drivers.lms111.errors import ProtocolError
from drivers.lms111.values import FLEXSTR, I32, U8, U16, U32, FieldType, ParamReader, Value

_DEG_PER_UNIT = 1e-4


def expect_reply(reply: Reply, kind: CommandType, name: str) -> None:
    if reply.kind is not kind or reply.name != name:
        raise ProtocolError(f"expected {kind.value} {name}, got {reply.kind.value} {reply.name}")


def as_ints(values: Sequence[Value]) -> tuple[int, ...]:
    if not all(isinstance(v, int) for v in values):
        raise ProtocolError(f"expected integers, got {values!r}")
    return tuple(int(v) for v in values)


@dataclass(frozen=True)
class ScanConfig:
    """Scan frequency, angular resolution and scan area, in the device's integer units."""

    scan_frequency_100th_hz: int
    angular_resolution_10000th_deg: int
    start_angle_10000th_deg: int = -450_000
    stop_angle_10000th_deg: int = 2_250_000
    sector_count: int = 1

    @classmethod
    def from_si(
        cls,
        scan_frequency_hz: float,
        angular_resolution_deg: float,
        start_angle_deg: float = -45.0,
        stop_angle_deg: float = 225.0,
    ) -> ScanConfig:
        return cls(
            round(scan_frequency_hz * 100),
            round(angular_resolution_deg * 10_000),
            round(start_angle_deg * 10_000),
            round(stop_angle_deg * 10_000),
        )

    @property
    def scan_frequency_hz(self) -> float:
        return self.scan_frequency_100th_hz / 100.0

    @property
    def angular_resolution_deg(self) -> float:
        return self.angular_resolution_10000th_deg * _DEG_PER_UNIT

    @property
    def start_angle_deg(self) -> float:
        return self.start_angle_10000th_deg * _DEG_PER_UNIT

    @property
    def stop_angle_deg(self) -> float:
        return self.stop_angle_10000th_deg * _DEG_PER_UNIT

    @property
    def angular_resolution_rad(self) -> float:
        return math.radians(self.angular_resolution_deg)

    @property
    def start_angle_rad(self) -> float:
        return math.radians(self.start_angle_deg)

    @property
    def stop_angle_rad(self) -> float:
        return math.radians(self.stop_angle_deg)


SET_SCAN_CONFIG_STATUS = {
    0: "no error",
    1: "frequency error",
    2: "angular resolution error",
    3: "frequency and angular resolution error",
    4: "scan area error",
    5: "other error",
}


@dataclass(frozen=True)
class SetScanConfigResult:
    status: int
    config: ScanConfig  # what the device applied

    @property
    def ok(self) -> bool:
        return self.status == 0

    @property
    def meaning(self) -> str:
        return SET_SCAN_CONFIG_STATUS.get(self.status, f"unknown status {self.status}")


class LmsState(enum.IntEnum):
    """``STlms`` state codes."""

    UNDEFINED = 0
    INITIALISATION = 1
    CONFIGURATION = 2
    IDLE = 3
    ROTATED = 4
    IN_PREPARATION = 5
    READY = 6
    MEASURING = 7  # "ready for measurement": the state a working scanner reports


@dataclass(frozen=True)
class DeviceStatus:
    """``STlms``: the scanner's own health summary."""

    state: int
    temperature_out_of_range: bool
    time_text: str  # device clock "HH:MM:SS"
    date_text: str  # "DD.MM.YYYY"
    led1: int = 0
    led2: int = 0
    led3: int = 0

    @property
    def measuring(self) -> bool:
        return self.state == LmsState.MEASURING


class DeviceState(enum.IntEnum):
    """``SCdevicestate``."""

    BUSY = 0
    READY = 1
    ERROR = 2


@dataclass(frozen=True)
class DeviceIdent:
    name: str
    version: str


def read_scan_sectors(reader: ParamReader, frequency_100th_hz: int) -> ScanConfig:
    """Sector count then per sector (resolution, start, stop); the first sector is kept."""
    count = reader.read_int(U16)
    if count < 1:
        raise ProtocolError("scan configuration with no sector")
    sectors = [as_ints([reader.read_int(U32), reader.read_int(I32), reader.read_int(I32)])]
    sectors += [
        as_ints([reader.read_int(U32), reader.read_int(I32), reader.read_int(I32)])
        for _ in range(count - 1)
    ]
    resolution, start, stop = sectors[0]
    return ScanConfig(frequency_100th_hz, resolution, start, stop, count)


def parse_access_mode(reply: Reply) -> bool:
    """True if ``sAN SetAccessMode`` granted the user level."""
    expect_reply(reply, CommandType.SAN, "SetAccessMode")
    (granted,) = as_ints(reply.decode((U8,)))
    return granted == 1


def parse_scan_config(reply: Reply) -> ScanConfig:
    expect_reply(reply, CommandType.SRA, "LMPscancfg")
    reader = reply.reader()
    config = read_scan_sectors(reader, reader.read_int(U32))
    reader.expect_end()
    return config


def parse_set_scan_config(reply: Reply) -> SetScanConfigResult:
    expect_reply(reply, CommandType.SAN, "mLMPsetscancfg")
    reader = reply.reader()
    status = reader.read_int(U8)
    config = read_scan_sectors(reader, reader.read_int(U32))
    reader.expect_end()
    return SetScanConfigResult(status, config)


def parse_output_range(reply: Reply) -> ScanConfig:
    """``sRA LMPoutputRange`` as a ScanConfig without frequency (0)."""
    expect_reply(reply, CommandType.SRA, "LMPoutputRange")
    reader = reply.reader()
    config = read_scan_sectors(reader, 0)
    reader.expect_end()
    return config


def parse_device_status(reply: Reply) -> DeviceStatus:
    expect_reply(reply, CommandType.SRA, "STlms")
    reader = reply.reader()
    state = reader.read_int(U16)
    hot = reader.read_int(U8)
    time_text = reader.read_str(FLEXSTR)
    date_text = reader.read_str(FLEXSTR)
    leds = [reader.read_int(U16) for _ in range(3)]
    return DeviceStatus(state, bool(hot), time_text, date_text, *leds)


def parse_method_status(reply: Reply, name: str) -> int:
    """The one status value of a method answer (``sAN LMCstartmeas 0``, ``sAN Run 1``)."""
    expect_reply(reply, CommandType.SAN, name)
    (status,) = as_ints(reply.decode((U8,)))
    return status


def parse_event_answer(reply: Reply) -> bool:
    """``sEA <event> 1``: the subscription is now on (True) or off."""
    if reply.kind is not CommandType.SEA:
        raise ProtocolError(f"expected sEA, got {reply.kind.value} {reply.name}")
    (enabled,) = as_ints(reply.decode((U8,)))
    return enabled == 1


def parse_device_state(reply: Reply) -> int:
    """0 busy, 1 ready, 2 error (`DeviceState`); other values are passed through."""
    expect_reply(reply, CommandType.SRA, "SCdevicestate")
    (state,) = as_ints(reply.decode((U8,)))
    return state


def parse_device_ident(reply: Reply) -> DeviceIdent:
    expect_reply(reply, CommandType.SRA, "DeviceIdent")
    name, version = reply.decode((FLEXSTR, FLEXSTR))
    return DeviceIdent(str(name), str(version))


def parse_string_variable(reply: Reply, name: str) -> str:
    """``sRA FirmwareVersion`` / ``sRA LocationName``: one flexible string."""
    expect_reply(reply, CommandType.SRA, name)
    (text,) = reply.decode((FLEXSTR,))
    return str(text)


# --- The twin's side: answers in the same shapes. ---

Fields = tuple[tuple[FieldType, Value], ...]


def _sector_fields(config: ScanConfig) -> Fields:
    return (
        (U16, 1),
        (U32, config.angular_resolution_10000th_deg),
        (I32, config.start_angle_10000th_deg),
        (I32, config.stop_angle_10000th_deg),
    )


def answer_access_mode(granted: bool) -> Command:
    return Command(CommandType.SAN, "SetAccessMode", ((U8, int(granted)),))


def answer_scan_config(config: ScanConfig) -> Command:
    fields = ((U32, config.scan_frequency_100th_hz), *_sector_fields(config))
    return Command(CommandType.SRA, "LMPscancfg", fields)


def answer_set_scan_config(status: int, applied: ScanConfig) -> Command:
    fields = ((U8, status), (U32, applied.scan_frequency_100th_hz), *_sector_fields(applied))
    return Command(CommandType.SAN, "mLMPsetscancfg", fields)


def answer_output_range(output_range: ScanConfig) -> Command:
    return Command(CommandType.SRA, "LMPoutputRange", _sector_fields(output_range))


def answer_device_status(status: DeviceStatus) -> Command:
    fields: Fields = (
        (U16, status.state),
        (U8, int(status.temperature_out_of_range)),
        (FLEXSTR, status.time_text),
        (FLEXSTR, status.date_text),
        (U16, status.led1),
        (U16, status.led2),
        (U16, status.led3),
    )
    return Command(CommandType.SRA, "STlms", fields)


def answer_method(name: str, status: int | None = None) -> Command:
    """``sAN <method> <status>`` (or without a status: ``sAN mSCreboot``)."""
    fields: Fields = () if status is None else ((U8, status),)
    return Command(CommandType.SAN, name, fields)


def answer_write(name: str) -> Command:
    """``sWA <variable>``: a write was accepted."""
    return Command(CommandType.SWA, name)


def answer_event(name: str, enabled: bool) -> Command:
    return Command(CommandType.SEA, name, ((U8, int(enabled)),))


def answer_device_state(state: int) -> Command:
    return Command(CommandType.SRA, "SCdevicestate", ((U8, state),))


def answer_device_ident(ident: DeviceIdent) -> Command:
    return Command(
        CommandType.SRA, "DeviceIdent", ((FLEXSTR, ident.name), (FLEXSTR, ident.version))
    )


def answer_string_variable(name: str, text: str) -> Command:
    """``sRA FirmwareVersion <string>`` / ``sRA LocationName <string>``."""
    return Command(CommandType.SRA, name, ((FLEXSTR, text),))
