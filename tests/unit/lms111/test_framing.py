"""Framing: the fragmentation matrix, resync rules and the fuzz property, both dialects."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.lms111 import NEED_DATA, ColaFramer, Dialect, ProtocolError, Telegram, frame
from drivers.lms111.errors import TruncatedTelegram
from tests.unit.lms111.golden import SCAN_COLA_A, SCAN_COLA_B, SCAN_COLA_B_PAYLOAD

PAYLOAD_A = SCAN_COLA_A[1:-1]
REPLY_A = b"\x02sAN SetAccessMode 1\x03"
GOLDEN = {Dialect.COLA_A: SCAN_COLA_A, Dialect.COLA_B: SCAN_COLA_B}
PAYLOAD = {Dialect.COLA_A: PAYLOAD_A, Dialect.COLA_B: SCAN_COLA_B_PAYLOAD}


def drain(framer: ColaFramer) -> list[Telegram | ProtocolError]:
    """Everything the framer yields now, errors included (it stays usable after one)."""
    out: list[Telegram | ProtocolError] = []
    while True:
        try:
            event = framer.next_event()
        except ProtocolError as exc:
            out.append(exc)
            continue
        if event is NEED_DATA:
            return out
        out.append(event)


def feed(framer: ColaFramer, chunks: list[bytes]) -> list[Telegram | ProtocolError]:
    out: list[Telegram | ProtocolError] = []
    for chunk in chunks:
        framer.receive_data(chunk)
        out += drain(framer)
    return out


def payloads(events: list[Telegram | ProtocolError]) -> list[bytes]:
    return [e.payload for e in events if isinstance(e, Telegram)]


@pytest.mark.parametrize("dialect", list(Dialect))
def test_one_telegram_in_one_read(dialect: Dialect) -> None:
    framer = ColaFramer(dialect)
    assert payloads(feed(framer, [GOLDEN[dialect]])) == [PAYLOAD[dialect]]
    assert framer.buffered_bytes == 0
    assert framer.garbage_bytes == framer.malformed_telegrams == 0


@pytest.mark.parametrize("dialect", list(Dialect))
def test_split_at_every_offset(dialect: Dialect) -> None:
    data = GOLDEN[dialect]
    for cut in range(len(data) + 1):
        framer = ColaFramer(dialect)
        events = feed(framer, [data[:cut], data[cut:]])
        assert events == [Telegram(dialect, PAYLOAD[dialect])], cut


@pytest.mark.parametrize("dialect", list(Dialect))
def test_byte_by_byte(dialect: Dialect) -> None:
    data = GOLDEN[dialect]
    framer = ColaFramer(dialect)
    events = feed(framer, [data[i : i + 1] for i in range(len(data))])
    assert payloads(events) == [PAYLOAD[dialect]]
    assert len(events) == 1


@pytest.mark.parametrize("dialect", list(Dialect))
def test_several_telegrams_in_one_read(dialect: Dialect) -> None:
    run = b"sAN Run \x01" if dialect is Dialect.COLA_B else b"sAN Run 1"
    framer = ColaFramer(dialect)
    events = feed(framer, [GOLDEN[dialect] + frame(dialect, run) + GOLDEN[dialect]])
    assert payloads(events) == [PAYLOAD[dialect], run, PAYLOAD[dialect]]


@pytest.mark.parametrize("dialect", list(Dialect))
def test_leading_and_trailing_garbage(dialect: Dialect) -> None:
    framer = ColaFramer(dialect)
    events = feed(framer, [b"\xff\x00junk" + GOLDEN[dialect] + b"tail"])
    assert payloads(events) == [PAYLOAD[dialect]]
    assert framer.garbage_bytes == 6 + 4  # "tail" holds no start marker: dropped at once
    framer.receive_data(REPLY_A if dialect is Dialect.COLA_A else frame(dialect, b"sAN Run \x01"))
    assert len(payloads(drain(framer))) == 1
    assert framer.garbage_bytes == 10


def test_cola_a_truncated_telegram_then_good_one() -> None:
    framer = ColaFramer(Dialect.COLA_A)
    events = feed(framer, [SCAN_COLA_A[:200], SCAN_COLA_A])
    assert isinstance(events[0], ProtocolError)
    assert payloads(events) == [PAYLOAD_A]
    assert framer.malformed_telegrams == 1


def test_cola_a_truncated_then_good_one_in_one_read() -> None:
    framer = ColaFramer(Dialect.COLA_A)
    events = feed(framer, [b"\x02sSN LMDscan" + REPLY_A])
    assert [type(e) for e in events] == [TruncatedTelegram, Telegram]  # a ProtocolError
    assert isinstance(events[0], ProtocolError)
    assert payloads(events) == [REPLY_A[1:-1]]


def test_cola_b_corrupted_checksum_then_good_one() -> None:
    bad = bytearray(SCAN_COLA_B)
    bad[-1] ^= 0x55
    framer = ColaFramer(Dialect.COLA_B)
    events = feed(framer, [bytes(bad) + SCAN_COLA_B])
    assert isinstance(events[0], ProtocolError)
    assert payloads(events) == [SCAN_COLA_B_PAYLOAD]
    assert framer.malformed_telegrams == 1


def test_cola_b_corrupted_payload_byte_then_good_one_split() -> None:
    bad = bytearray(SCAN_COLA_B)
    bad[40] ^= 0x01
    framer = ColaFramer(Dialect.COLA_B)
    events = feed(framer, [bytes(bad), SCAN_COLA_B[:10], SCAN_COLA_B[10:]])
    assert payloads(events) == [SCAN_COLA_B_PAYLOAD]
    assert framer.malformed_telegrams == 1


def test_cola_b_corrupted_length_hides_a_good_telegram_that_still_comes_out() -> None:
    """A too-short (but plausible) length: the search restarts inside, and finds the next."""
    run = frame(Dialect.COLA_B, b"sAN Run \x01")
    bad = b"\x02\x02\x02\x02\x00\x00\x00\x30" + b"x" * 10
    framer = ColaFramer(Dialect.COLA_B)
    events = feed(framer, [bad + SCAN_COLA_B + run])
    assert payloads(events) == [SCAN_COLA_B_PAYLOAD, run[8:-1]]


def test_cola_b_length_above_cap_is_dropped() -> None:
    framer = ColaFramer(Dialect.COLA_B, max_telegram_bytes=100)
    events = feed(framer, [SCAN_COLA_B + frame(Dialect.COLA_B, b"sAN Run \x01")])
    assert isinstance(events[0], ProtocolError)
    assert payloads(events) == [b"sAN Run \x01"]


def test_cola_a_overlong_telegram_is_dropped_and_stream_continues() -> None:
    framer = ColaFramer(Dialect.COLA_A, max_telegram_bytes=100, max_buffer_bytes=1000)
    events = feed(framer, [b"\x02" + b"A" * 150, b"B" * 10 + b"\x03" + REPLY_A])
    assert isinstance(events[0], ProtocolError)
    assert payloads(events) == [REPLY_A[1:-1]]


def test_buffer_overflow_drops_oldest_bytes() -> None:
    framer = ColaFramer(Dialect.COLA_B, max_telegram_bytes=100, max_buffer_bytes=200)
    framer.receive_data(b"\x00" * 500)
    assert framer.buffered_bytes == 200
    assert framer.garbage_bytes == 300


def test_empty_cola_a_telegram_is_malformed() -> None:
    framer = ColaFramer(Dialect.COLA_A)
    events = feed(framer, [b"\x02\x03" + REPLY_A])
    assert [type(e) for e in events] == [ProtocolError, Telegram]


def test_switch_dialect_keeps_buffer() -> None:
    framer = ColaFramer(Dialect.COLA_A)
    framer.receive_data(b"\x02sWA EIHstCola\x03" + SCAN_COLA_B)
    assert framer.next_event() == Telegram(Dialect.COLA_A, b"sWA EIHstCola")
    framer.switch_dialect(Dialect.COLA_B)
    assert framer.next_event() == Telegram(Dialect.COLA_B, SCAN_COLA_B_PAYLOAD)


def test_reset_forgets_everything() -> None:
    framer = ColaFramer(Dialect.COLA_A)
    framer.receive_data(b"junk\x02partial")
    drain(framer)
    framer.reset()
    assert framer.buffered_bytes == framer.garbage_bytes == framer.malformed_telegrams == 0


def test_frame_rejects_what_cannot_be_framed() -> None:
    with pytest.raises(ProtocolError):
        frame(Dialect.COLA_A, b"")
    with pytest.raises(ProtocolError):
        frame(Dialect.COLA_A, b"sAN \x03 x")


@st.composite
def chunked(draw: st.DrawFn, data: bytes) -> list[bytes]:
    cuts = sorted(draw(st.lists(st.integers(0, len(data)), max_size=12)))
    edges = [0, *cuts, len(data)]
    return [data[a:b] for a, b in itertools.pairwise(edges)]


_STREAM_PIECES = st.one_of(
    st.binary(max_size=40),
    st.sampled_from([SCAN_COLA_A, SCAN_COLA_B, REPLY_A, b"\x02", b"\x03", b"\x02\x02\x02\x02"]),
)


@settings(max_examples=150, deadline=None)
@given(
    dialect=st.sampled_from(list(Dialect)),
    pieces=st.lists(_STREAM_PIECES, max_size=8),
    data=st.data(),
)
def test_arbitrary_bytes_only_yield_telegrams_or_protocol_errors(
    dialect: Dialect, pieces: list[bytes], data: st.DataObject
) -> None:
    framer = ColaFramer(dialect, max_telegram_bytes=4096, max_buffer_bytes=8192)
    stream = b"".join(pieces)
    for chunk in data.draw(chunked(stream)):
        framer.receive_data(chunk)
        assert framer.buffered_bytes <= 8192
        for event in drain(framer):  # anything but ProtocolError propagates and fails
            assert isinstance(event, Telegram | ProtocolError)
        assert framer.buffered_bytes <= 8192


@settings(max_examples=60, deadline=None)
@given(dialect=st.sampled_from(list(Dialect)), data=st.data())
def test_a_good_telegram_after_garbage_always_comes_out(
    dialect: Dialect, data: st.DataObject
) -> None:
    """Whatever precedes it (without start markers), a complete telegram is delivered."""
    garbage = data.draw(st.binary(max_size=64).map(lambda b: b.replace(b"\x02", b"")))
    framer = ColaFramer(dialect)
    events = feed(framer, data.draw(chunked(garbage + GOLDEN[dialect])))
    assert payloads(events) == [PAYLOAD[dialect]]
