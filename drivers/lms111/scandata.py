"""``LMDscandata``: the scan telegram, decoded into SI units and encoded back.

Layout (parameters after ``sSN LMDscandata`` / ``sRA LMDscandata``), from the LMS500 and
LMS4000 operating instructions' telegram tables and SICK's "Telegram Listing Ranging
sensors" as implemented by Wireshark's ``packet-cola.c``; the CoLa-A spelling of the tail
blocks was checked against a real LMS telegram (``... 0 1 B not defined 0 1 7B2 1 1 0 33 2B
79568 0``):

==============================  ===================  =====================================
field                           type                 note
==============================  ===================  =====================================
version                         uint16               1
device number                   uint16               set in SOPAS
serial number                   uint32
device status                   2 x uint8            0 0 = ok
telegram counter, scan counter  uint16 each
time since start-up             uint32, µs           wraps after ~71.6 min (`timebase`)
time of transmission            uint32, µs
digital inputs, outputs         2 x uint8 each
reserved (layer angle)          uint16               0 on a single-layer LMS1xx
scan frequency                  uint32, 1/100 Hz     5000 = 50 Hz
measurement frequency           uint32, 100 Hz       0x168 = 36 kHz
encoders                        uint16 n, then n x (uint32 position, uint16 speed)
16-bit channels                 uint16 n, then n x channel (below)
8-bit channels                  uint16 n, then n x channel with uint8 data
position                        uint16 flag; 6 x REAL (x, y, z, rot x, y, z), uint8
                                rotation type, uint8 "transmit device name"
device name, comment            uint16 flag; flexible string
time                            uint16 flag; uint16 year, 5 x uint8 (month .. second),
                                uint32 µs
event info                      uint16 flag; 4-char type (``FDIN``), uint32 encoder
                                position, uint32 time µs, int32 angle 1/10000°
==============================  ===================  =====================================

A channel is: 5-char content (``DIST1``, ``RSSI1`` ...), REAL scale factor, REAL scale offset,
int32 start angle (1/10000°), uint16 angular step (1/10000°), uint16 count, then the data.
A distance value is ``raw * scale + offset`` in millimetres; raw 0 means "no echo".

The position block's trailing uint8 appears in the current listing (and Wireshark) but not
in the 2010 LMS500 manual; an LMS111 never sends the block. Parsing is strict (trailing bytes
are an error), so a device that disagreed would fail loudly rather than decode garbage.
"""

from __future__ import annotations

import math

from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import Dialect
from drivers.lms111.scan import Channel, Encoder, Position, Scan, ScanEvent, ScanTimestamp
from drivers.lms111.values import (
    F32,
    FLEXSTR,
    I32,
    U8,
    U16,
    U32,
    CType,
    ParamReader,
    ParamWriter,
    fixstr,
)

_CHANNEL_NAME = fixstr(5)
_EVENT_TYPE = fixstr(4)


def _read_flag(reader: ParamReader, block: str) -> bool:
    flag = reader.read_int(U16)
    if flag > 1:
        raise ProtocolError(f"{block} flag is {flag}, expected 0 or 1")
    return flag == 1


def _read_two_bytes(reader: ParamReader) -> int:
    return (reader.read_int(U8) << 8) | reader.read_int(U8)


def _read_channels(reader: ParamReader, ctype: CType) -> tuple[Channel, ...]:
    channels = []
    for _ in range(reader.read_int(U16)):
        name = reader.read_str(_CHANNEL_NAME)
        scale_factor = reader.read_float()
        scale_offset = reader.read_float()
        if not (math.isfinite(scale_factor) and math.isfinite(scale_offset)):
            raise ProtocolError(f"{name}: non-finite scale factor or offset")
        start = reader.read_int(I32)
        step = reader.read_int(U16)
        data = reader.read_array(reader.read_int(U16), ctype)
        channels.append(Channel(name, scale_factor, scale_offset, start, step, data))
    return tuple(channels)


def decode_scan(
    dialect: Dialect, params: bytes, *, host_receive_time_s: float | None = None
) -> Scan:
    """Decode the parameters of an ``LMDscandata`` telegram; `ProtocolError` if malformed."""
    r = ParamReader(dialect, params)
    header = (
        r.read_int(U16),
        r.read_int(U16),
        r.read_int(U32),
        _read_two_bytes(r),
        r.read_int(U16),
        r.read_int(U16),
        r.read_int(U32),
        r.read_int(U32),
        _read_two_bytes(r),
        _read_two_bytes(r),
        r.read_int(U16),
        r.read_int(U32),
        r.read_int(U32),
    )
    encoders = tuple(Encoder(r.read_int(U32), r.read_int(U16)) for _ in range(r.read_int(U16)))
    channels_16bit = _read_channels(r, CType.U16)
    channels_8bit = _read_channels(r, CType.U8)
    position = None
    if _read_flag(r, "position"):
        x, y, z, rot_x, rot_y, rot_z = (r.read_float() for _ in range(6))
        position = Position(x, y, z, rot_x, rot_y, rot_z, r.read_int(U8), r.read_int(U8))
    device_name = r.read_str(FLEXSTR) if _read_flag(r, "device name") else None
    comment = r.read_str(FLEXSTR) if _read_flag(r, "comment") else None
    timestamp = None
    if _read_flag(r, "time"):
        year = r.read_int(U16)
        month, day, hour, minute, second = (r.read_int(U8) for _ in range(5))
        timestamp = ScanTimestamp(year, month, day, hour, minute, second, r.read_int(U32))
    event = None
    if _read_flag(r, "event info"):
        event = ScanEvent(
            r.read_str(_EVENT_TYPE), r.read_int(U32), r.read_int(U32), r.read_int(I32)
        )
    r.expect_end()
    (version, device_number, serial, status, telegrams, scans, time_us, transmit_us) = header[:8]
    inputs, outputs, reserved, frequency, measurement = header[8:]
    return Scan(
        channels_16bit=channels_16bit,
        channels_8bit=channels_8bit,
        version=version,
        device_number=device_number,
        serial_number=serial,
        device_status=status,
        telegram_counter=telegrams,
        scan_counter=scans,
        device_time_us=time_us,
        transmit_time_us=transmit_us,
        input_status=inputs,
        output_status=outputs,
        reserved=reserved,
        scan_frequency_100th_hz=frequency,
        measurement_frequency_100hz=measurement,
        encoders=encoders,
        position=position,
        device_name=device_name,
        comment=comment,
        timestamp=timestamp,
        event=event,
        host_receive_time_s=host_receive_time_s,
    )


def _write_two_bytes(writer: ParamWriter, value: int) -> None:
    if not 0 <= value <= 0xFFFF:
        raise ProtocolError(f"{value} does not fit two status bytes")
    writer.write(U8, value >> 8)
    writer.write(U8, value & 0xFF)


def _write_channels(writer: ParamWriter, channels: tuple[Channel, ...], ctype: CType) -> None:
    writer.write(U16, len(channels))
    for channel in channels:
        writer.write(_CHANNEL_NAME, channel.name)
        writer.write(F32, channel.scale_factor)
        writer.write(F32, channel.scale_offset)
        writer.write(I32, channel.start_angle_10000th_deg)
        writer.write(U16, channel.angular_step_10000th_deg)
        writer.write(U16, len(channel.data))
        writer.write_array(channel.data, ctype)


def encode_scan_params(scan: Scan, dialect: Dialect) -> bytes:
    """The parameter bytes of an ``LMDscandata`` telegram (what the twin sends)."""
    w = ParamWriter(dialect)
    for ft, value in (
        (U16, scan.version),
        (U16, scan.device_number),
        (U32, scan.serial_number),
    ):
        w.write(ft, value)
    _write_two_bytes(w, scan.device_status)
    for ft, value in (
        (U16, scan.telegram_counter),
        (U16, scan.scan_counter),
        (U32, scan.device_time_us),
        (U32, scan.transmit_time_us),
    ):
        w.write(ft, value)
    _write_two_bytes(w, scan.input_status)
    _write_two_bytes(w, scan.output_status)
    w.write(U16, scan.reserved)
    w.write(U32, scan.scan_frequency_100th_hz)
    w.write(U32, scan.measurement_frequency_100hz)
    w.write(U16, len(scan.encoders))
    for encoder in scan.encoders:
        w.write(U32, encoder.position_ticks)
        w.write(U16, encoder.speed_ticks_per_mm)
    _write_channels(w, scan.channels_16bit, CType.U16)
    _write_channels(w, scan.channels_8bit, CType.U8)
    w.write(U16, scan.position is not None)
    if scan.position is not None:
        p = scan.position
        for coordinate in (p.x, p.y, p.z, p.rotation_x, p.rotation_y, p.rotation_z):
            w.write(F32, coordinate)
        w.write(U8, p.rotation_type)
        w.write(U8, p.transmit_device_name)
    for text in (scan.device_name, scan.comment):
        w.write(U16, text is not None)
        if text is not None:
            w.write(FLEXSTR, text)
    w.write(U16, scan.timestamp is not None)
    if scan.timestamp is not None:
        t = scan.timestamp
        w.write(U16, t.year)
        for calendar_field in (t.month, t.day, t.hour, t.minute, t.second):
            w.write(U8, calendar_field)
        w.write(U32, t.microsecond)
    w.write(U16, scan.event is not None)
    if scan.event is not None:
        e = scan.event
        w.write(_EVENT_TYPE, e.event_type)
        w.write(U32, e.encoder_position_ticks)
        w.write(U32, e.event_time_us)
        w.write(I32, e.angular_position_10000th_deg)
    return w.getvalue()
