"""The scan encoders against a plain reference encoding written here, byte for byte.

The twins' encoders are vectorised (`ParamWriter.write_array` spells a whole channel in one
numpy pass; the header fields go through per-type tables). They must send exactly what a
straightforward encoding sends: the reference below follows the telegram listing field by
field, one ``%X`` or ``int.to_bytes`` per value, and shares no code with
``drivers.lms111.values``. Whole telegrams are also decoded back with the project's decoder.
"""

from __future__ import annotations

import functools
import math
import operator
import struct
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.sim import Pose2D, load_site
from appliance.sim.twins.lms111 import Lms111Twin
from drivers.lms111 import (
    Channel,
    CommandType,
    Dialect,
    Encoder,
    Lms111Connection,
    Position,
    ProtocolError,
    Scan,
    ScanEvent,
    ScanTelegram,
    ScanTimestamp,
    encode_scan_telegram,
)
from drivers.lms111.cola import parse_telegram
from drivers.lms111.framing import Telegram
from drivers.lms111.replies import ScanConfig
from drivers.lms111.twin_device import DeviceModel
from drivers.lms111.values import (
    F32,
    FLEXSTR,
    FLEXSTR_DEC,
    I16,
    I32,
    I32_DEC,
    U8,
    U8_HEX2,
    U16,
    U16_DEC,
    U32,
    U32_DEC,
    U32_HEX8,
    CType,
    FieldType,
    ParamWriter,
    Style,
    hex_tokens,
)

# ---- the reference: one value at a time, straight from the listing -----------------------


def ref_uint(dialect: Dialect, value: int, size: int) -> bytes:
    """An unsigned field of ``size`` bytes: hex without leading zeros / big-endian."""
    assert 0 <= value < 1 << (8 * size)
    return b"%X" % value if dialect is Dialect.COLA_A else value.to_bytes(size, "big")


def ref_int32(dialect: Dialect, value: int) -> bytes:
    """A signed int32: two's complement in hex (``FFF92230`` = -450000) / big-endian."""
    if dialect is Dialect.COLA_A:
        return b"%X" % (value + (1 << 32) if value < 0 else value)
    return value.to_bytes(4, "big", signed=True)


def ref_real(dialect: Dialect, value: float) -> bytes:
    packed = struct.pack(">f", value)
    return b"%08X" % int.from_bytes(packed, "big") if dialect is Dialect.COLA_A else packed


def ref_flexstr(dialect: Dialect, text: str) -> bytes:
    raw = text.encode("latin-1")
    if dialect is Dialect.COLA_B:
        return len(raw).to_bytes(2, "big") + raw
    return b"%X" % len(raw) + (b" " + raw if raw else b"")


def ref_channel_data(dialect: Dialect, values: Sequence[int], size: int) -> list[bytes]:
    """One part per value: ``%X`` tokens (joined by spaces later) or big-endian bytes."""
    return [ref_uint(dialect, int(v), size) for v in values]


def ref_scan_params(scan: Scan, dialect: Dialect) -> bytes:
    """The LMDscandata parameters, field by field as in `drivers.lms111.scandata`'s table."""
    parts: list[bytes] = []
    u8, u16, u32 = (functools.partial(ref_uint, dialect, size=n) for n in (1, 2, 4))

    def add(*fields: bytes) -> None:
        parts.extend(fields)

    add(u16(scan.version), u16(scan.device_number), u32(scan.serial_number))
    add(u8(scan.device_status >> 8), u8(scan.device_status & 0xFF))
    add(u16(scan.telegram_counter), u16(scan.scan_counter))
    add(u32(scan.device_time_us), u32(scan.transmit_time_us))
    for status in (scan.input_status, scan.output_status):
        add(u8(status >> 8), u8(status & 0xFF))
    add(u16(scan.reserved), u32(scan.scan_frequency_100th_hz))
    add(u32(scan.measurement_frequency_100hz))
    add(u16(len(scan.encoders)))
    for encoder in scan.encoders:
        add(u32(encoder.position_ticks), u16(encoder.speed_ticks_per_mm))
    for channels, size in ((scan.channels_16bit, 2), (scan.channels_8bit, 1)):
        add(u16(len(channels)))
        for channel in channels:
            add(channel.name.encode("latin-1"))
            add(ref_real(dialect, channel.scale_factor), ref_real(dialect, channel.scale_offset))
            add(ref_int32(dialect, channel.start_angle_10000th_deg))
            add(u16(channel.angular_step_10000th_deg), u16(len(channel.data)))
            parts.extend(ref_channel_data(dialect, channel.data.tolist(), size))
    add(u16(scan.position is not None))
    if scan.position is not None:
        p = scan.position
        for value in (p.x, p.y, p.z, p.rotation_x, p.rotation_y, p.rotation_z):
            add(ref_real(dialect, value))
        add(u8(p.rotation_type), u8(p.transmit_device_name))
    for text in (scan.device_name, scan.comment):
        add(u16(text is not None))
        if text is not None:
            add(ref_flexstr(dialect, text))
    add(u16(scan.timestamp is not None))
    if scan.timestamp is not None:
        t = scan.timestamp
        add(u16(t.year), *(u8(v) for v in (t.month, t.day, t.hour, t.minute, t.second)))
        add(u32(t.microsecond))
    add(u16(scan.event is not None))
    if scan.event is not None:
        e = scan.event
        add(e.event_type.encode("latin-1"), u32(e.encoder_position_ticks), u32(e.event_time_us))
        add(ref_int32(dialect, e.angular_position_10000th_deg))
    return (b" " if dialect is Dialect.COLA_A else b"").join(parts)


def ref_telegram(scan: Scan, dialect: Dialect, kind: bytes = b"sSN") -> bytes:
    payload = kind + b" LMDscandata " + ref_scan_params(scan, dialect)
    if dialect is Dialect.COLA_A:
        return b"\x02" + payload + b"\x03"
    checksum = functools.reduce(operator.xor, payload, 0)
    return b"\x02\x02\x02\x02" + len(payload).to_bytes(4, "big") + payload + bytes([checksum])


# ---- strategies: channel data with the edge values over-represented ------------------------

EDGES_16 = [0, 1, 0xF, 0x10, 0xFF, 0x100, 0xFFF, 0x1000, 0xFFFE, 0xFFFF]
EDGES_8 = [0, 1, 0xF, 0x10, 0xFE, 0xFF]


def channel_values(bits: int) -> st.SearchStrategy[list[int]]:
    top = (1 << bits) - 1
    edges = EDGES_16 if bits == 16 else EDGES_8
    value = st.one_of(st.sampled_from(edges), st.integers(0, top))
    return st.one_of(
        st.lists(value, max_size=64),
        st.builds(long_values, st.integers(0, 2**32 - 1), st.integers(65, 1200), st.just(bits)),
        # whole scans of one value (all "no echo", all saturated) at the LMS111's lengths
        st.builds(lambda v, n: [v] * n, st.sampled_from([0, top]), st.sampled_from([541, 1081])),
    )


_u16 = st.integers(0, 0xFFFF)
_u32 = st.integers(0, 0xFFFFFFFF)
_i32 = st.integers(-(1 << 31), (1 << 31) - 1)
_f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
_text = st.text(st.characters(min_codepoint=0x20, max_codepoint=0xFF), max_size=12)


def _frozen(values: list[int], dtype: npt.DTypeLike) -> npt.NDArray[np.unsignedinteger]:
    data = np.array(values, dtype=dtype)
    data.flags.writeable = False
    return data


def long_values(seed: int, count: int, bits: int) -> list[int]:
    """Random values of a whole scan (drawing 1,081 integers one by one is slow)."""
    rng = np.random.default_rng(seed)
    values = rng.integers(0, 1 << bits, count)
    edges = EDGES_16 if bits == 16 else EDGES_8
    where = rng.random(count) < 0.2
    values[where] = rng.choice(edges, int(where.sum()))
    return [int(v) for v in values]


@st.composite
def scans(draw: st.DrawFn) -> Scan:
    """Any scan the encoder accepts: short channels of any length, and whole scans."""
    count = draw(st.integers(0, 40) | st.sampled_from([540, 541, 1081, 1200]))
    step = draw(_u16)
    start = draw(_i32)

    def channel(name: str, bits: int) -> Channel:
        top = (1 << bits) - 1
        if count <= 40:  # one byte string, then edge values at drawn places (cheap to draw)
            raw = draw(st.binary(min_size=count * bits // 8, max_size=count * bits // 8))
            values = np.frombuffer(raw, dtype="<u2" if bits == 16 else "u1").tolist()
            edges = EDGES_16 if bits == 16 else EDGES_8
            for where, edge in draw(st.lists(st.tuples(_u16, st.sampled_from(edges)), max_size=6)):
                if values:
                    values[where % len(values)] = edge
        else:
            values = draw(
                st.builds(long_values, _u32, st.just(count), st.just(bits))
                | st.builds(lambda v: [v] * count, st.sampled_from([0, top]))
            )
        dtype = np.uint16 if bits == 16 else np.uint8
        return Channel(name, draw(_f32), draw(_f32), start, step, _frozen(values, dtype))

    names16 = draw(st.sampled_from([["DIST1"], ["DIST1", "RSSI1"], ["DIST1", "DIST2"]]))
    names8 = draw(st.sampled_from([[], ["RSSI1"]]))
    return Scan(
        channels_16bit=tuple(channel(name, 16) for name in names16),
        channels_8bit=tuple(channel(name, 8) for name in names8),
        version=draw(_u16),
        device_number=draw(_u16),
        serial_number=draw(_u32),
        device_status=draw(_u16),
        telegram_counter=draw(_u16),
        scan_counter=draw(_u16),
        device_time_us=draw(_u32),
        transmit_time_us=draw(_u32),
        input_status=draw(_u16),
        output_status=draw(_u16),
        reserved=draw(_u16),
        scan_frequency_100th_hz=draw(_u32),
        measurement_frequency_100hz=draw(_u32),
        encoders=tuple(Encoder(draw(_u32), draw(_u16)) for _ in range(draw(st.integers(0, 2)))),
        position=draw(
            st.none()
            | st.builds(
                Position, _f32, _f32, _f32, _f32, _f32, _f32, st.integers(0, 3), st.integers(0, 1)
            )
        ),
        device_name=draw(st.none() | _text),
        comment=draw(st.none() | _text),
        timestamp=draw(
            st.none() | st.builds(ScanTimestamp, _u16, *[st.integers(0, 255)] * 5, _u32)
        ),
        event=draw(st.none() | st.builds(ScanEvent, st.just("FDIN"), _u32, _u32, _i32)),
    )


def decode_wire(wire: bytes, dialect: Dialect) -> Scan:
    connection = Lms111Connection(dialect)
    connection.receive_data(wire)
    event = connection.next_event()
    assert isinstance(event, ScanTelegram)
    return event.scan


def assert_same_scan(sent: Scan, received: Scan) -> None:
    for name in ("telegram_counter", "scan_counter", "device_time_us", "serial_number"):
        assert getattr(received, name) == getattr(sent, name), name
    assert (received.device_name, received.comment) == (sent.device_name, sent.comment)
    assert (received.timestamp, received.event) == (sent.timestamp, sent.event)
    for mine, theirs in (
        (sent.channels_16bit, received.channels_16bit),
        (sent.channels_8bit, received.channels_8bit),
    ):
        assert [c.name for c in mine] == [c.name for c in theirs]
        for a, b in zip(mine, theirs, strict=True):
            assert a.data.dtype == b.data.dtype
            np.testing.assert_array_equal(a.data, b.data)


# ---- the channel spelling ------------------------------------------------------------------


def test_hex_tokens_spell_every_16_bit_value_as_the_reference_does() -> None:
    values = np.arange(1 << 16, dtype=np.uint16)
    assert hex_tokens(values, 4) == b" ".join(b"%X" % v for v in range(1 << 16))
    assert hex_tokens(values[::-1], 4) == b" ".join(b"%X" % v for v in reversed(range(1 << 16)))


def test_hex_tokens_spell_every_8_bit_value_as_the_reference_does() -> None:
    values = np.arange(256, dtype=np.uint8)
    assert hex_tokens(values, 2) == b" ".join(b"%X" % v for v in range(256))


@pytest.mark.parametrize("values", [[], [0], [0xFFFF], [0, 0xFFFF, 0], [0x10, 0xF, 0x100]])
@pytest.mark.parametrize("dialect", list(Dialect))
def test_short_channels_between_other_fields(dialect: Dialect, values: list[int]) -> None:
    writer = ParamWriter(dialect)
    writer.write(U16, len(values))
    writer.write_array(np.array(values, dtype=np.uint16), CType.U16)
    writer.write(U16, 0xABC)
    parts = [ref_uint(dialect, len(values), 2), *ref_channel_data(dialect, values, 2)]
    parts.append(ref_uint(dialect, 0xABC, 2))
    assert writer.getvalue() == (b" " if dialect is Dialect.COLA_A else b"").join(parts)


@settings(max_examples=300, deadline=None)
@given(
    dialect=st.sampled_from(list(Dialect)),
    bits=st.sampled_from([8, 16]),
    data=st.data(),
)
def test_channel_data_is_byte_identical_to_the_reference(
    dialect: Dialect, bits: int, data: st.DataObject
) -> None:
    values = data.draw(channel_values(bits))
    # The twin sends native uint16/uint8; other integer arrays must spell the same way.
    dtypes = ["<u2", ">u2", "<i8", "<u4"] if bits == 16 else ["u1", "<u2", "<i8"]
    array = np.array(values, dtype=data.draw(st.sampled_from(dtypes)))
    if data.draw(st.booleans()):  # a strided view (every other value of a longer array)
        array = np.repeat(array, 2)[::2]
    ctype = CType.U16 if bits == 16 else CType.U8
    writer = ParamWriter(dialect)
    writer.write(U8, 0x7)
    writer.write_array(array, ctype)
    writer.write(U8, 0x8)
    size = bits // 8
    parts = [ref_uint(dialect, 7, 1), *ref_channel_data(dialect, values, size)]
    parts.append(ref_uint(dialect, 8, 1))
    assert writer.getvalue() == (b" " if dialect is Dialect.COLA_A else b"").join(parts)


@pytest.mark.parametrize("dialect", list(Dialect))
@pytest.mark.parametrize(
    ("values", "dtype", "ctype"),
    [
        ([0, -1], np.int64, CType.U16),
        ([0, 0x10000], np.int64, CType.U16),
        ([0x100, 0], np.uint16, CType.U8),
        ([-1], np.int16, CType.U8),
    ],
)
def test_channel_data_out_of_range_is_refused(
    dialect: Dialect, values: list[int], dtype: npt.DTypeLike, ctype: CType
) -> None:
    with pytest.raises(ProtocolError, match="channel data out of range"):
        ParamWriter(dialect).write_array(np.array(values, dtype=dtype), ctype)


@pytest.mark.parametrize("dialect", list(Dialect))
def test_signed_channel_data_keeps_its_decimal_minus(dialect: Dialect) -> None:
    """A signed type is not a channel type, but writes as it always did: ``%X`` of -5."""
    writer = ParamWriter(dialect)
    writer.write_array(np.array([-5, 0, 31], dtype=np.int16), CType.I16)
    expected = b"-5 0 1F" if dialect is Dialect.COLA_A else struct.pack(">3h", -5, 0, 31)
    assert writer.getvalue() == expected


# ---- the header fields ---------------------------------------------------------------------

_INT_FIELDS: list[tuple[FieldType, int, bool]] = [  # field, bytes, signed
    (U8, 1, False),
    (U8_HEX2, 1, False),
    (U16, 2, False),
    (U16_DEC, 2, False),
    (U32, 4, False),
    (U32_HEX8, 4, False),
    (U32_DEC, 4, False),
    (I16, 2, True),
    (I32, 4, True),
    (I32_DEC, 4, True),
    (FieldType(CType.I8), 1, True),
]


def ref_int_field(dialect: Dialect, ft: FieldType, size: int, signed: bool, value: int) -> bytes:
    if dialect is Dialect.COLA_B:
        return value.to_bytes(size, "big", signed=signed)
    if ft.style is Style.DEC:
        return (b"+" if value >= 0 else b"-") + str(abs(value)).encode()
    raw = value % (1 << (8 * size))
    width = {Style.HEX: 0, Style.HEX2: 2, Style.HEX8: 8}[ft.style]
    return format(raw, "X").rjust(width, "0").encode()


@settings(max_examples=400, deadline=None)
@given(field=st.sampled_from(_INT_FIELDS), dialect=st.sampled_from(list(Dialect)), data=st.data())
def test_integer_fields_are_byte_identical_to_the_reference(
    field: tuple[FieldType, int, bool], dialect: Dialect, data: st.DataObject
) -> None:
    ft, size, signed = field
    lo, hi = (
        (-(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1) if signed else (0, (1 << 8 * size) - 1)
    )
    value = data.draw(
        st.one_of(st.sampled_from([lo, hi, 0, 1, -1 if signed else 2]), st.integers(lo, hi))
    )
    writer = ParamWriter(dialect)
    writer.write(ft, value)
    assert writer.getvalue() == ref_int_field(dialect, ft, size, signed, value)
    for bad in (lo - 1, hi + 1):
        with pytest.raises(ProtocolError, match="out of range"):
            ParamWriter(dialect).write(ft, bad)
    with pytest.raises(ProtocolError, match="needs an int"):
        ParamWriter(dialect).write(ft, 1.5)


@settings(max_examples=200, deadline=None)
@given(value=_f32, text=_text, dialect=st.sampled_from(list(Dialect)))
def test_real_and_string_fields_are_byte_identical_to_the_reference(
    value: float, text: str, dialect: Dialect
) -> None:
    writer = ParamWriter(dialect)
    writer.write(F32, value)
    writer.write(FLEXSTR, text)
    separator = b" " if dialect is Dialect.COLA_A else b""
    assert writer.getvalue() == ref_real(dialect, value) + separator + ref_flexstr(dialect, text)
    if dialect is Dialect.COLA_A:  # the decimal-length spelling of a request's string
        decimal = ParamWriter(dialect)
        decimal.write(FLEXSTR_DEC, text)
        raw = text.encode("latin-1")
        assert decimal.getvalue() == b"%+d" % len(raw) + (b" " + raw if raw else b"")


# ---- whole telegrams -----------------------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(scan=scans(), dialect=st.sampled_from(list(Dialect)))
def test_whole_scan_telegrams_are_byte_identical_and_decode_back(
    scan: Scan, dialect: Dialect
) -> None:
    wire = encode_scan_telegram(scan, dialect)
    assert wire == ref_telegram(scan, dialect)
    assert encode_scan_telegram(scan, dialect, CommandType.SRA) == ref_telegram(
        scan, dialect, b"sRA"
    )
    assert_same_scan(scan, decode_wire(wire, dialect))


def _world(
    beams: int, seed: int
) -> Callable[[float, npt.NDArray[np.float64]], tuple[npt.NDArray[np.float64], ...]]:
    """Ranges with no-echo beams, short ones and beams beyond a uint16 of millimetres."""
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.0, 30.0, beams)
    ranges[rng.random(beams) < 0.1] = 0.0
    ranges[:3] = (0.0, 0.0005, 70.0)  # no echo, rounds to 0 mm, saturates at 0xFFFF
    remission = rng.uniform(0.0, 5.0, beams)  # retro-reflectors saturate the 16-bit RSSI
    return lambda _t_s, _angles: (ranges, remission)


@pytest.mark.parametrize("dialect", list(Dialect))
@pytest.mark.parametrize(("hz", "deg"), [(50.0, 0.5), (25.0, 0.25)])
@pytest.mark.parametrize("remission_16bit", [True, False])
def test_the_devices_telegrams_are_byte_identical_to_the_reference(
    dialect: Dialect, hz: float, deg: float, remission_16bit: bool
) -> None:
    config = ScanConfig.from_si(hz, deg)
    beams = 541 if deg == 0.5 else 1081
    device = DeviceModel(_world(beams, seed=beams), dialect=dialect, config=config)
    device.data_config = replace(device.data_config, remission_16bit=remission_16bit, time=True)
    connection = Lms111Connection(dialect)
    for i in range(3):
        scan = device.measure(1.0 + i * device.period_s)
        assert scan is not None
        assert len(scan.channels_16bit[0].data) == beams
        telegram = device.telegram(scan)
        assert telegram.telegram_counter == i + 1 and scan.telegram_counter == 0
        wire = connection.send_scan(telegram)
        assert wire == ref_telegram(telegram, dialect)
        received = decode_wire(wire, dialect)
        assert_same_scan(telegram, received)
        assert received.ranges_m[2] == pytest.approx(65.535)


@pytest.mark.parametrize("dialect", list(Dialect))
def test_a_twins_rendered_scan_is_byte_identical_to_the_reference(dialect: Dialect) -> None:
    twin = Lms111Twin(
        load_site("launcher"),
        Pose2D(2.6, 1.1, math.radians(45.0)),
        lambda t_s: Pose2D(-10.0 + t_s, 0.3, math.radians(2.0)),
        dialect=dialect,
    )
    scan = twin.device.measure(1.0)
    assert scan is not None
    telegram = twin.device.telegram(scan)
    wire = Lms111Connection(dialect).send_scan(telegram)
    assert wire == ref_telegram(telegram, dialect)
    event = parse_telegram(
        Telegram(dialect, wire[1:-1] if dialect is Dialect.COLA_A else wire[8:-1])
    )
    assert isinstance(event, ScanTelegram)
    assert_same_scan(telegram, event.scan)
    assert np.count_nonzero(event.scan.ranges_m) > 100  # the launcher site is in view
