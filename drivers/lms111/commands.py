"""Requests the LMS111 driver sends, and how a twin reads them back.

Each request is described once (command type, name, typed fields) and encoded to either
dialect by `Command.encode`. The CoLa-A spellings follow the telegram listing's examples
byte for byte (``sMN SetAccessMode 03 F4724744``, ``sMN mLMPsetscancfg +5000 +1 +5000
-450000 +2250000``, ``sWN LMDscandatacfg 01 00 1 1 0 00 00 0 0 0 0 +1``); in CoLa-B the same
fields become big-endian binary (``sMN SetAccessMode `` + ``03 F4 72 47 44``).

Sources: SICK LMS1xx/LMS500/LMS4000 operating instructions (telegram annex), SICK's
``sick_scan_xd`` (ASCII/binary test vectors), clearpath ``LMS1xx`` and Wireshark's CoLa
dissector for the binary field widths.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.lms111.cola import Command, CommandType, Reply
from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import Dialect
from drivers.lms111.replies import ScanConfig, as_ints, expect_reply, read_scan_sectors
from drivers.lms111.values import (
    I32,
    I32_DEC,
    U8,
    U8_HEX2,
    U16,
    U16_DEC,
    U32,
    U32_DEC,
    U32_HEX8,
    FieldType,
    Value,
)

AUTHORIZED_CLIENT = 3
AUTHORIZED_CLIENT_PASSWORD = 0xF4724744  # the documented default for "authorised client"
MAINTENANCE = 2
MAINTENANCE_PASSWORD = 0xB21ACE26

_ACCESS_MODE_FIELDS = (U8_HEX2, U32_HEX8)
_SET_SCAN_CONFIG_FIELDS = (U32_DEC, U16_DEC, U32_DEC, I32_DEC, I32_DEC)
_SCAN_DATA_CONFIG_FIELDS = (U8_HEX2, U8_HEX2, U8, U8, U8, U8_HEX2, U8_HEX2, U8, U8, U8, U8)
_OUTPUT_RANGE_FIELDS = (U16, U32, I32, I32)


def _fields(
    types: tuple[FieldType, ...], values: tuple[Value, ...]
) -> tuple[tuple[FieldType, Value], ...]:
    return tuple(zip(types, values, strict=True))


def set_access_mode(
    user_level: int = AUTHORIZED_CLIENT, password_hash: int = AUTHORIZED_CLIENT_PASSWORD
) -> Command:
    """Log in (``sMN SetAccessMode``); needed before any configuration write."""
    return Command(
        CommandType.SMN, "SetAccessMode", _fields(_ACCESS_MODE_FIELDS, (user_level, password_hash))
    )


def set_scan_config(config: ScanConfig) -> Command:
    """``sMN mLMPsetscancfg``: frequency (1/100 Hz), sectors, resolution, start, stop (1/10000°).

    The device answers with the values it actually applied (`replies.parse_set_scan_config`).
    """
    values = (
        config.scan_frequency_100th_hz,
        config.sector_count,
        config.angular_resolution_10000th_deg,
        config.start_angle_10000th_deg,
        config.stop_angle_10000th_deg,
    )
    return Command(CommandType.SMN, "mLMPsetscancfg", _fields(_SET_SCAN_CONFIG_FIELDS, values))


@dataclass(frozen=True)
class ScanDataConfig:
    """What each scan telegram carries (``sWN LMDscandatacfg``), in the listing's order.

    ``output_channel`` is a bit mask of echoes (1 = first, 2 = second, 3 = both); the byte
    after it and after ``encoder`` is reserved (always 0). ``remission_16bit`` picks the
    RSSI resolution (False = 8 bit); ``remission_unit`` 0 = digits. ``output_interval`` 1
    sends every scan, n every n-th (1 .. 50000).
    """

    output_channel: int = 1
    remission: bool = True
    remission_16bit: bool = True
    remission_unit: int = 0
    encoder: int = 0
    position: bool = False
    device_name: bool = False
    comment: bool = False
    time: bool = False
    output_interval: int = 1


def configure_scan_data(config: ScanDataConfig) -> Command:
    c = config
    values: tuple[Value, ...] = (
        c.output_channel,
        0,
        int(c.remission),
        int(c.remission_16bit),
        c.remission_unit,
        c.encoder,
        0,
        int(c.position),
        int(c.device_name),
        int(c.comment),
        int(c.time),
    )
    fields = (*_fields(_SCAN_DATA_CONFIG_FIELDS, values), (U16_DEC, c.output_interval))
    return Command(CommandType.SWN, "LMDscandatacfg", fields)


def set_output_range(
    angular_resolution_10000th_deg: int, start_angle_10000th_deg: int, stop_angle_10000th_deg: int
) -> Command:
    """``sWN LMPoutputRange 1 <resolution> <start> <stop>``: limit the angles sent per scan."""
    values = (1, angular_resolution_10000th_deg, start_angle_10000th_deg, stop_angle_10000th_deg)
    return Command(CommandType.SWN, "LMPoutputRange", _fields(_OUTPUT_RANGE_FIELDS, values))


def _bare(kind: CommandType, name: str) -> Command:
    return Command(kind, name)


def read_scan_config() -> Command:
    return _bare(CommandType.SRN, "LMPscancfg")


def read_output_range() -> Command:
    return _bare(CommandType.SRN, "LMPoutputRange")


def start_measurement() -> Command:
    """``sMN LMCstartmeas``: laser on, motor up to speed (answer ``sAN LMCstartmeas 0``)."""
    return _bare(CommandType.SMN, "LMCstartmeas")


def stop_measurement() -> Command:
    return _bare(CommandType.SMN, "LMCstopmeas")


def run() -> Command:
    """``sMN Run``: log out and apply the configuration (answer ``sAN Run 1``)."""
    return _bare(CommandType.SMN, "Run")


def save_parameters() -> Command:
    """``sMN mEEwriteall``: make the configuration survive a power cycle."""
    return _bare(CommandType.SMN, "mEEwriteall")


def subscribe(event_name: str, enable: bool = True) -> Command:
    """``sEN <event> 1`` (or 0 to stop): LMDscandata, LFErec, LIDoutputstate, LIDinputstate."""
    return Command(CommandType.SEN, event_name, ((U8, int(enable)),))


def subscribe_scans(enable: bool = True) -> Command:
    """``sEN LMDscandata 1``: stream every scan as ``sSN LMDscandata`` until sent with 0."""
    return subscribe("LMDscandata", enable)


def poll_scan() -> Command:
    """``sRN LMDscandata``: one scan, answered as ``sRA LMDscandata``."""
    return _bare(CommandType.SRN, "LMDscandata")


def read_device_status() -> Command:
    return _bare(CommandType.SRN, "STlms")


def read_device_state() -> Command:
    return _bare(CommandType.SRN, "SCdevicestate")


def read_device_ident() -> Command:
    return _bare(CommandType.SRN, "DeviceIdent")


def read_firmware_version() -> Command:
    return _bare(CommandType.SRN, "FirmwareVersion")


def read_location_name() -> Command:
    return _bare(CommandType.SRN, "LocationName")


def set_cola_dialect(dialect: Dialect) -> Command:
    """``sWN EIHstCola 0`` (CoLa-A) / ``1`` (CoLa-B); the answer comes in the old dialect."""
    return Command(CommandType.SWN, "EIHstCola", ((U8, int(dialect is Dialect.COLA_B)),))


# --- The twin's side: read the requests above back into values. ---


def parse_set_access_mode_request(request: Reply) -> tuple[int, int]:
    """(user level, password hash) from ``sMN SetAccessMode``."""
    expect_reply(request, CommandType.SMN, "SetAccessMode")
    level, password = as_ints(request.decode(_ACCESS_MODE_FIELDS))
    return level, password


def parse_set_scan_config_request(request: Reply) -> ScanConfig:
    expect_reply(request, CommandType.SMN, "mLMPsetscancfg")
    reader = request.reader()
    frequency = reader.read_int(U32)
    config = read_scan_sectors(reader, frequency)
    reader.expect_end()
    return config


def parse_scan_data_config_request(request: Reply) -> ScanDataConfig:
    expect_reply(request, CommandType.SWN, "LMDscandatacfg")
    ints = as_ints(request.decode((*_SCAN_DATA_CONFIG_FIELDS, U16_DEC)))
    channel, _, remission, bits16, unit, encoder, _, pos, name, comment, time, interval = ints
    return ScanDataConfig(
        output_channel=channel,
        remission=bool(remission),
        remission_16bit=bool(bits16),
        remission_unit=unit,
        encoder=encoder,
        position=bool(pos),
        device_name=bool(name),
        comment=bool(comment),
        time=bool(time),
        output_interval=interval,
    )


def parse_event_request(request: Reply) -> bool:
    """Whether ``sEN <event> n`` subscribes (1) or unsubscribes (0)."""
    if request.kind is not CommandType.SEN:
        raise ProtocolError(f"expected sEN, got {request.kind.value} {request.name}")
    (enable,) = as_ints(request.decode((U8,)))
    if enable not in (0, 1):
        raise ProtocolError(f"sEN {request.name} {enable}: expected 0 or 1")
    return enable == 1


def parse_set_dialect_request(request: Reply) -> Dialect:
    expect_reply(request, CommandType.SWN, "EIHstCola")
    (value,) = as_ints(request.decode((U8,)))
    if value not in (0, 1):
        raise ProtocolError(f"EIHstCola {value}: expected 0 (CoLa-A) or 1 (CoLa-B)")
    return Dialect.COLA_B if value == 1 else Dialect.COLA_A
