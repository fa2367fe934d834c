"""The receiver: line splitting, the checksum rule, counters, bounds and the fuzz property."""

from __future__ import annotations

import itertools

import pynmea2
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.gnss import (
    GgaFix,
    GstError,
    Heading,
    NmeaEvent,
    NmeaReceiver,
    Reject,
    RmcFix,
    VtgVelocity,
    nmea_checksum,
)
from tests.unit.gnss.lines import feed, parse_all, sentence, xor_checksum
from tests.unit.gnss.test_sentences import GGA, GST, HDT, RMC, THS, VTG

EVENT_TYPES = (GgaFix, RmcFix, VtgVelocity, Heading, GstError)
STREAM = b"".join(sentence(b) for b in (GGA, RMC, VTG, HDT, THS, GST))


def test_a_stream_of_every_type() -> None:
    events, receiver = parse_all(STREAM)
    assert [type(e) for e in events] == [GgaFix, RmcFix, VtgVelocity, Heading, Heading, GstError]
    assert receiver.counts == {}
    assert receiver.buffered_bytes == receiver.garbage_bytes == 0


def test_checksum_function_agrees_with_the_independent_one() -> None:
    for body in (GGA, RMC, VTG, HDT, THS, GST, ""):
        assert nmea_checksum(body) == xor_checksum(body)


@pytest.mark.parametrize("eol", [b"\r\n", b"\n", b"\r"])
def test_line_endings(eol: bytes) -> None:
    events, _ = parse_all(sentence(GGA, eol=eol) + sentence(VTG, eol=eol))
    assert [type(e) for e in events] == [GgaFix, VtgVelocity]


def test_split_at_every_byte_position_gives_the_same_events() -> None:
    whole, _ = parse_all(STREAM)
    for cut in range(len(STREAM) + 1):
        receiver = NmeaReceiver()
        assert feed(receiver, [STREAM[:cut], STREAM[cut:]]) == whole, cut
        assert receiver.counts == {}


def test_byte_by_byte() -> None:
    whole, _ = parse_all(STREAM)
    receiver = NmeaReceiver()
    assert feed(receiver, [STREAM[i : i + 1] for i in range(len(STREAM))]) == whole


def test_a_sentence_without_its_line_end_waits() -> None:
    receiver = NmeaReceiver()
    assert feed(receiver, [sentence(GGA, eol=b"")]) == []
    assert feed(receiver, [b"\n"]) != []


def test_garbage_before_the_start_is_dropped_and_counted() -> None:
    events, receiver = parse_all(b"\x00\xffjunk" + sentence(GGA) + b"7,A*1F\r\n" + sentence(VTG))
    assert [type(e) for e in events] == [GgaFix, VtgVelocity]
    assert receiver.garbage_bytes == 6 + 6  # the fragment of a sentence cut off at power-up
    assert receiver.counts == {Reject.NO_START: 1}
    assert receiver.error_count == 1


def test_a_sentence_glued_onto_a_fragment_is_kept() -> None:
    """A lost line end glues the rest of one sentence to the next: ``$`` is reserved, so
    the last one on the line starts the sentence worth reading."""
    fragment = sentence(RMC)[:30]  # cut off mid-sentence, its CR LF lost
    events, receiver = parse_all(fragment + sentence(GGA))
    assert [type(e) for e in events] == [GgaFix]
    assert receiver.garbage_bytes == len(fragment)
    assert receiver.error_count == 0


def test_bad_checksum_is_counted_and_kept_for_diagnostics() -> None:
    bad = bytearray(sentence(GGA))
    bad[20] = ord("9") if bad[20] != ord("9") else ord("8")  # one digit of the latitude
    events, receiver = parse_all(bytes(bad) + sentence(RMC))
    assert [type(e) for e in events] == [RmcFix]
    assert receiver.counts == {Reject.CHECKSUM: 1}
    assert receiver.last_bad_reason is Reject.CHECKSUM
    assert receiver.last_bad_line == bytes(bad).rstrip(b"\r\n")


@pytest.mark.parametrize("body", [GGA, THS])
def test_a_missing_checksum_is_an_error(body: str) -> None:
    events, receiver = parse_all(f"${body}\r\n".encode())
    assert events == []
    assert receiver.counts == {Reject.NO_CHECKSUM: 1}


@pytest.mark.parametrize("suffix", ["*4", "*", "*4G", "*47 ", "*47*47"])
def test_a_garbled_checksum_field_is_malformed(suffix: str) -> None:
    events, receiver = parse_all(f"${GGA}{suffix}\r\n".encode())
    assert events == []
    assert receiver.counts == {Reject.MALFORMED: 1}


def test_ths_checksum_is_checked_though_pynmea2_does_not_know_ths() -> None:
    line = bytearray(sentence(THS))
    line[-4] ^= 0x01  # last checksum digit
    events, receiver = parse_all(bytes(line))
    assert events == []
    assert receiver.counts == {Reject.CHECKSUM: 1}


@pytest.mark.parametrize(
    "line",
    [
        sentence("GPGSV,3,1,11,03,03,111,00,04,15,270,00,06,01,010,00,13,06,292,00"),
        sentence("GNGSA,A,3,21,5,29,25,12,10,26,2,,,,,1.2,0.7,1.0"),
        sentence("GPZDA,201530.00,04,07,2002,00,00"),
        sentence("PUBX,00,081350.00,4717.113210,N,00833.915187,E,546.589"),
        sentence("PGRME,15.0,M,45.0,M,25.0,M"),
        sentence("AIVDM,1,1,,A,13aEOK?P00PD2wVMdLDRhgvL289?,0", start="!"),
        sentence("GPXYZ,1,2,3"),
        sentence("XXTHX,1,2"),
    ],
)
def test_other_sentence_types_are_ignored_not_errors(line: bytes) -> None:
    events, receiver = parse_all(line)
    assert events == []
    assert receiver.counts == {Reject.IGNORED_TYPE: 1}
    assert receiver.error_count == 0
    assert receiver.last_bad_line is None


def test_too_long_line_is_dropped_whole_and_the_stream_continues() -> None:
    long_line = sentence("GPTXT," + "A" * 200)
    for chunks in ([long_line + sentence(GGA)], [long_line[:150], long_line[150:], sentence(GGA)]):
        receiver = NmeaReceiver()
        events = feed(receiver, chunks)
        assert [type(e) for e in events] == [GgaFix]
        assert receiver.counts == {Reject.TOO_LONG: 1}
        assert receiver.last_bad_line == long_line[:96]


def test_a_line_of_exactly_the_limit_is_read() -> None:
    body = GGA + "," * (128 - len(GGA) - 4)  # extra empty fields: still a GGA
    line = sentence(body)
    assert len(line.rstrip(b"\r\n")) == 128
    events, receiver = parse_all(line)
    assert [type(e) for e in events] == [GgaFix], receiver.counts


@pytest.mark.parametrize("bad", [b"\xb5", b"\x00", b"\t", b"\x7f", "é".encode()])
def test_non_ascii_or_control_bytes_in_a_sentence(bad: bytes) -> None:
    line = sentence(GGA).replace(b",N,", b"," + bad + b"N,")
    events, receiver = parse_all(line + sentence(VTG))
    assert [type(e) for e in events] == [VtgVelocity]
    assert receiver.counts == {Reject.NOT_ASCII: 1}


def test_anything_pynmea2_raises_is_counted_as_malformed(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(line: str, check: bool = False) -> None:
        raise RuntimeError("a bug in a proprietary sentence parser")

    monkeypatch.setattr(pynmea2, "parse", broken)
    events, receiver = parse_all(sentence(GGA))
    assert events == []
    assert receiver.counts == {Reject.MALFORMED: 1}


def test_buffer_is_bounded_when_the_caller_does_not_drain() -> None:
    receiver = NmeaReceiver(max_line_bytes=128, max_buffer_bytes=1000)
    for _ in range(40):
        receiver.receive_data(sentence(GGA))
        assert receiver.buffered_bytes <= 1000
    assert receiver.overflow_bytes > 0
    assert receiver.counts[Reject.OVERFLOW] > 0
    events = list(receiver.events())
    assert events
    assert all(isinstance(e, GgaFix) for e in events)
    assert receiver.counts.keys() == {Reject.OVERFLOW}  # the cut line was dropped, not misread
    assert feed(receiver, [sentence(RMC)]) != []


def test_reset_forgets_everything() -> None:
    receiver = NmeaReceiver()
    receiver.receive_data(b"junk\r\n$GPGGA,1\r\n" + sentence(GGA)[:20])
    list(receiver.events())
    receiver.reset()
    assert receiver.counts == {}
    assert receiver.buffered_bytes == receiver.garbage_bytes == receiver.overflow_bytes == 0
    assert receiver.last_bad_line is None
    assert receiver.last_bad_reason is None


@pytest.mark.parametrize(("line_bytes", "buffer_bytes"), [(81, 4096), (128, 128)])
def test_limits_are_checked(line_bytes: int, buffer_bytes: int) -> None:
    with pytest.raises(ValueError, match="max_line_bytes"):
        NmeaReceiver(max_line_bytes=line_bytes, max_buffer_bytes=buffer_bytes)


def _chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    edges = [0, *sorted(c % (len(data) + 1) for c in cuts), len(data)]
    return [data[a:b] for a, b in itertools.pairwise(edges)]


_GOOD = [sentence(b) for b in (GGA, RMC, VTG, HDT, THS, GST)]
_PIECES = st.one_of(
    st.binary(max_size=60),
    st.sampled_from([*_GOOD, b"$", b"!", b"*", b"\r", b"\n", b",", b"$GPGGA,", b"*47"]),
    st.sampled_from(_GOOD).map(lambda s: s[: len(s) // 2]),
    st.text(alphabet="$GPNRMCVTHSE0123456789.,*AW-", max_size=40).map(str.encode),
)


@settings(max_examples=300)
@given(pieces=st.lists(_PIECES, max_size=12), cuts=st.lists(st.integers(0, 10_000), max_size=10))
def test_any_bytes_whole_or_chunked_give_declared_events_or_counts(
    pieces: list[bytes], cuts: list[int]
) -> None:
    stream = b"".join(pieces)
    whole = NmeaReceiver(max_buffer_bytes=8192)
    whole_events = feed(whole, [stream])
    for chunks in (_chunked(stream, cuts), [stream[i : i + 1] for i in range(len(stream))]):
        receiver = NmeaReceiver(max_buffer_bytes=8192)
        events: list[NmeaEvent] = []
        for chunk in chunks:
            receiver.receive_data(chunk)
            events += receiver.events()  # any exception here fails the property
            assert receiver.buffered_bytes <= 128
        assert all(isinstance(e, EVENT_TYPES) for e in events)
        assert events == whole_events
        assert receiver.counts == whole.counts
        assert receiver.garbage_bytes == whole.garbage_bytes


@settings(max_examples=100)
@given(garbage=st.binary(max_size=200), data=st.data())
def test_a_good_sentence_after_any_garbage_line_comes_out(
    garbage: bytes, data: st.DataObject
) -> None:
    stream = garbage + b"\r\n" + sentence(GGA)
    receiver = NmeaReceiver(max_line_bytes=128, max_buffer_bytes=512)
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=8))
    events = feed(receiver, _chunked(stream, cuts))
    assert events
    assert isinstance(events[-1], GgaFix)
    assert receiver.buffered_bytes == 0


_FIELD_TEXT = st.text(alphabet="0123456789.-+NSEWATVMKNXe_ ", max_size=12)


@settings(max_examples=400)
@given(
    address=st.sampled_from(["GPGGA", "GNRMC", "GLVTG", "INHDT", "INTHS", "GPGST"]),
    fields=st.lists(_FIELD_TEXT, max_size=16),
)
def test_any_fields_behind_a_good_checksum_give_an_event_or_a_field_reason(
    address: str, fields: list[str]
) -> None:
    """The field readers raise nothing but their own error, whatever a verified line holds."""
    events, receiver = parse_all(sentence(",".join([address, *fields])))
    if events:
        assert len(events) == 1
        assert isinstance(events[0], EVENT_TYPES)
        assert receiver.counts == {}
    else:
        assert receiver.counts.keys() <= {Reject.MALFORMED, Reject.OUT_OF_RANGE, Reject.TOO_LONG}
