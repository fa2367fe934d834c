"""LMDscandata: golden telegrams, encode/decode round trips, and fuzzing of the decoder."""

from __future__ import annotations

import contextlib
import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.lms111 import (
    NEED_DATA,
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
    decode_scan,
    encode_scan_params,
    encode_scan_telegram,
    scan_from_ranges,
)
from tests.unit.lms111.golden import SCAN_COLA_A, SCAN_COLA_B

GOLDEN = {Dialect.COLA_A: SCAN_COLA_A, Dialect.COLA_B: SCAN_COLA_B}


def receive_scan(dialect: Dialect, data: bytes, now_s: float | None = None) -> ScanTelegram:
    conn = Lms111Connection(dialect)
    conn.receive_data(data)
    event = conn.next_event(host_receive_time_s=now_s)
    assert isinstance(event, ScanTelegram)
    assert conn.next_event() is NEED_DATA
    return event


def assert_scans_equal(a: Scan, b: Scan) -> None:
    """Field by field; channel arrays by value (Scan holds arrays, so no dataclass eq)."""
    for field in dataclasses.fields(Scan):
        if field.name in ("channels_16bit", "channels_8bit"):
            continue
        assert getattr(a, field.name) == getattr(b, field.name), field.name
    for mine, theirs in ((a.channels_16bit, b.channels_16bit), (a.channels_8bit, b.channels_8bit)):
        assert len(mine) == len(theirs)
        for x, y in zip(mine, theirs, strict=True):
            assert (x.name, x.start_angle_10000th_deg, x.angular_step_10000th_deg) == (
                y.name,
                y.start_angle_10000th_deg,
                y.angular_step_10000th_deg,
            )
            assert np.float32(x.scale_factor) == np.float32(y.scale_factor)
            assert np.float32(x.scale_offset) == np.float32(y.scale_offset)
            assert x.data.dtype == y.data.dtype
            np.testing.assert_array_equal(x.data, y.data)


@pytest.mark.parametrize("dialect", list(Dialect))
def test_golden_scan_header(dialect: Dialect) -> None:
    event = receive_scan(dialect, GOLDEN[dialect], now_s=123.25)
    scan = event.scan
    assert event.kind is CommandType.SSN
    assert scan.version == 1
    assert scan.device_number == 1
    assert scan.serial_number == 0x89A27F
    assert scan.device_status == 0
    assert scan.telegram_counter == 1234
    assert scan.scan_counter == 1238
    assert scan.device_time_us == 0xA1B2C3D4
    assert scan.transmit_time_us == 0xA1B2D000
    assert (scan.input_status, scan.output_status, scan.reserved) == (0, 0, 0)
    assert scan.scan_frequency_100th_hz == 5000
    assert scan.scan_frequency_hz == 50.0
    assert scan.measurement_frequency_hz == 36_000.0
    assert scan.encoders == ()
    assert scan.channels_8bit == ()
    assert scan.position is None and scan.comment is None and scan.event is None
    assert scan.device_name == "LMS111 left"
    assert scan.timestamp == ScanTimestamp(2024, 5, 31, 23, 59, 58, 999_999)
    assert scan.host_receive_time_s == 123.25


@pytest.mark.parametrize("dialect", list(Dialect))
def test_golden_scan_points(dialect: Dialect) -> None:
    scan = receive_scan(dialect, GOLDEN[dialect]).scan
    dist = scan.channel("DIST1")
    assert dist is not None
    assert dist.scale_factor == 2.0
    assert dist.start_angle_10000th_deg == -450_000
    assert dist.angular_step_10000th_deg == 5000
    # raw mm x scale 2.0; raw 0 stays 0 ("no echo").
    np.testing.assert_allclose(scan.ranges_m, [0.0, 1.0, 2.0, 131.07, 4.0])
    np.testing.assert_allclose(np.degrees(scan.angles_rad), [-45.0, -44.5, -44.0, -43.5, -43.0])
    assert scan.angular_step_rad == pytest.approx(math.radians(0.5))
    assert scan.intensities is not None
    np.testing.assert_array_equal(scan.intensities, [0, 200, 254, 0, 100])
    assert set(scan.channels) == {"DIST1", "RSSI1"}
    assert not scan.ranges_m.flags.writeable and not dist.data.flags.writeable


@pytest.mark.parametrize("dialect", list(Dialect))
def test_golden_scan_reencodes_to_the_same_bytes(dialect: Dialect) -> None:
    scan = receive_scan(dialect, GOLDEN[dialect]).scan
    assert encode_scan_telegram(scan, dialect) == GOLDEN[dialect]


def test_polled_scan_is_a_scan_telegram_too() -> None:
    sra = SCAN_COLA_A.replace(b"sSN", b"sRA", 1)
    assert receive_scan(Dialect.COLA_A, sra).kind is CommandType.SRA


def test_decimal_spelled_data_takes_the_exact_fallback() -> None:
    telegram = SCAN_COLA_A.replace(b"5 0 1F4 3E8 FFFF 7D0", b"5 +0 +500 +1000 +65535 +2000")
    np.testing.assert_allclose(
        receive_scan(Dialect.COLA_A, telegram).scan.ranges_m, [0.0, 1.0, 2.0, 131.07, 4.0]
    )


@pytest.mark.parametrize(
    "mutation",
    [
        (b"1F4 3E8", b"1F4 3G8"),  # not a hex digit
        (b"1F4 3E8", b"1F4  3E8"),  # empty token
        (b"FFFF 7D0", b"10000 7D0"),  # does not fit a uint16
        (b"5 0 1F4", b"6 0 1F4"),  # count says one value more
        (b"0 1 7E8", b"0 2 7E8"),  # time flag must be 0 or 1
        (b"1 B LMS111 left", b"1 C LMS111 left"),  # string longer than the telegram's tokens
        (b"DIST1 40000000", b"DIST1 7FC00000"),  # NaN scale factor
        (b"F423F 0", b"F423F 0 0"),  # trailing token
        (b"F423F 0", b"F423F"),  # truncated
    ],
)
def test_malformed_cola_a_scans_raise_protocol_error(mutation: tuple[bytes, bytes]) -> None:
    conn = Lms111Connection()
    conn.receive_data(SCAN_COLA_A.replace(*mutation))
    with pytest.raises(ProtocolError):
        conn.next_event()
    assert conn.malformed_telegrams == 1
    conn.receive_data(SCAN_COLA_A)
    assert isinstance(conn.next_event(), ScanTelegram)


def test_truncated_cola_b_params_raise_protocol_error() -> None:
    params = encode_scan_params(receive_scan(Dialect.COLA_B, SCAN_COLA_B).scan, Dialect.COLA_B)
    for cut in range(0, len(params), 7):
        with pytest.raises(ProtocolError):
            decode_scan(Dialect.COLA_B, params[:cut])


def test_scan_from_ranges_matches_lms_conventions() -> None:
    ranges = np.array([0.0, 1.234, np.nan, 70.0, -1.0])
    scan = scan_from_ranges(ranges, intensities=[1, 2, 3, 4, 5])
    dist = scan.channel("DIST1")
    assert dist is not None and dist.scale_factor == 2.0  # a range above 65.535 m
    for dialect in Dialect:
        decoded = receive_scan(dialect, encode_scan_telegram(scan, dialect)).scan
        np.testing.assert_allclose(decoded.ranges_m, [0.0, 1.234, 0.0, 70.0, 0.0], atol=1e-3)


# --- Property tests. ---

_u16 = st.integers(0, 0xFFFF)
_u32 = st.integers(0, 0xFFFFFFFF)
_f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
_text = st.text(st.characters(min_codepoint=0x20, max_codepoint=0xFF), max_size=20)


@st.composite
def channels(draw: st.DrawFn, names: list[str], bits: int) -> tuple[Channel, ...]:
    count = draw(st.integers(0, 40))
    out = []
    for name in names:
        # One draw of raw bytes per channel, not one per value: cheap to generate (a scan
        # has up to 160 values), and every bit pattern is still possible.
        raw = draw(st.binary(min_size=count * bits // 8, max_size=count * bits // 8))
        data = np.frombuffer(raw, np.dtype("<u2") if bits == 16 else np.uint8).astype(
            np.uint16 if bits == 16 else np.uint8
        )
        data.flags.writeable = False
        out.append(
            Channel(
                name,
                draw(_f32),
                draw(_f32),
                draw(st.integers(-(1 << 31), (1 << 31) - 1)),
                draw(_u16),
                data,
            )
        )
    return tuple(out)


@st.composite
def scans(draw: st.DrawFn) -> Scan:
    with_rssi = draw(st.booleans())
    names16 = ["DIST1", "RSSI1"] if with_rssi else ["DIST1"]
    names8 = draw(st.sampled_from([[], ["RSSI1"], ["RSSI1", "RSSI2"]]))
    return Scan(
        channels_16bit=draw(channels(names16, 16)),
        channels_8bit=draw(channels(names8, 8)),
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
        event=draw(
            st.none()
            | st.builds(
                ScanEvent, st.just("FDIN"), _u32, _u32, st.integers(-(1 << 31), (1 << 31) - 1)
            )
        ),
    )


@settings(max_examples=120, deadline=None)
@given(scan=scans(), dialect=st.sampled_from(list(Dialect)))
def test_encode_decode_round_trip(scan: Scan, dialect: Dialect) -> None:
    decoded = receive_scan(dialect, encode_scan_telegram(scan, dialect)).scan
    assert_scans_equal(scan, decoded)


@settings(max_examples=150, deadline=None)
@given(
    tokens=st.lists(
        st.one_of(
            st.sampled_from(
                [
                    "0",
                    "1",
                    "2",
                    "5",
                    "DIST1",
                    "RSSI1",
                    "3F800000",
                    "FFF92230",
                    "+12",
                    "-3",
                    "FFFF",
                    "B",
                ]
            ),
            st.text("0123456789ABCDEFG+- x", min_size=0, max_size=9),
        ),
        max_size=60,
    )
)
def test_arbitrary_tokens_give_a_scan_or_a_protocol_error(tokens: list[str]) -> None:
    params = " ".join(tokens).encode()
    try:
        scan = decode_scan(Dialect.COLA_A, params)
    except ProtocolError:
        return
    scan.ranges_m, scan.angles_rad, scan.intensities  # noqa: B018 - the SI views must work too


@settings(max_examples=150, deadline=None)
@given(params=st.binary(max_size=200))
def test_arbitrary_binary_gives_a_scan_or_a_protocol_error(params: bytes) -> None:
    with contextlib.suppress(ProtocolError):
        decode_scan(Dialect.COLA_B, params)


@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_mutated_golden_telegrams_never_raise_anything_else(data: st.DataObject) -> None:
    dialect = data.draw(st.sampled_from(list(Dialect)))
    telegram = bytearray(GOLDEN[dialect])
    for _ in range(data.draw(st.integers(1, 4))):
        telegram[data.draw(st.integers(0, len(telegram) - 1))] = data.draw(st.integers(0, 255))
    conn = Lms111Connection(dialect)
    conn.receive_data(bytes(telegram))
    for _ in range(5):
        try:
            if conn.next_event() is NEED_DATA:
                break
        except ProtocolError:
            pass
