"""COBS, CRC-16 and the frame decoder: resync after noise, bounded buffer, one error type."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.actuators.framing import (
    MAX_ENCODED_FRAME_BYTES,
    ActuatorProtocolError,
    FrameDecoder,
    cobs_decode,
    cobs_encode,
    crc16_ccitt_false,
    frame,
    frame_packet,
)

bodies = st.binary(min_size=2, max_size=50)
chunkings = st.lists(st.integers(min_value=1, max_value=40), min_size=1, max_size=20)


def drain(decoder: FrameDecoder) -> tuple[list[bytes], int]:
    """Every packet the decoder can give now, and how many errors it raised on the way."""
    packets: list[bytes] = []
    errors = 0
    while True:
        try:
            packet = decoder.next_packet()
        except ActuatorProtocolError:
            errors += 1
            continue
        if packet is None:
            return packets, errors
        packets.append(packet)


def split(data: bytes, sizes: list[int]) -> list[bytes]:
    chunks, index, i = [], 0, 0
    while index < len(data):
        size = sizes[i % len(sizes)]
        chunks.append(data[index : index + size])
        index += size
        i += 1
    return chunks


def test_crc16_ccitt_false_check_value() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc16_ccitt_false(b"") == 0xFFFF


@given(st.binary(max_size=700))
def test_cobs_round_trip_and_no_zero_bytes(data: bytes) -> None:
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert len(encoded) <= len(data) + len(data) // 254 + 1
    assert cobs_decode(encoded) == data


def test_cobs_known_vectors() -> None:
    assert cobs_encode(b"") == b"\x01"
    assert cobs_encode(b"\x00") == b"\x01\x01"
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert cobs_encode(bytes(range(1, 255))) == b"\xff" + bytes(range(1, 255)) + b"\x01"


@pytest.mark.parametrize("bad", [b"\x05\x01", b"\x02\x00", b"\x03"])
def test_cobs_decode_rejects_malformed(bad: bytes) -> None:
    with pytest.raises(ActuatorProtocolError):
        cobs_decode(bad)


@given(st.lists(bodies, min_size=1, max_size=8), chunkings)
def test_frames_survive_any_chunking(packets: list[bytes], sizes: list[int]) -> None:
    decoder = FrameDecoder()
    received: list[bytes] = []
    for chunk in split(b"".join(frame(p) for p in packets), sizes):
        decoder.receive_data(chunk)
        got, errors = drain(decoder)
        assert errors == 0
        received += got
    assert received == packets
    assert decoder.stats.frames_ok == len(packets)


@given(st.binary(max_size=300), st.lists(bodies, min_size=1, max_size=5), chunkings)
def test_resync_after_noise(noise: bytes, packets: list[bytes], sizes: list[int]) -> None:
    """Whatever garbage comes first, every frame after it arrives intact."""
    decoder = FrameDecoder()
    received: list[bytes] = []
    for chunk in split(noise + b"".join(frame(p) for p in packets), sizes):
        decoder.receive_data(chunk)
        received += drain(decoder)[0]
    assert received[-len(packets) :] == packets


def test_a_decoder_starts_unsynchronised_and_ignores_the_partial_head() -> None:
    decoder = FrameDecoder()
    wire = frame(b"\x91\x01abc") + frame(b"\x91\x02def")
    decoder.receive_data(wire[5:])  # opened the port in the middle of the first frame
    packets, errors = drain(decoder)
    assert packets == [b"\x91\x02def"]
    assert errors == 0


def test_bad_crc_is_counted_dropped_and_the_next_frame_decodes() -> None:
    decoder = FrameDecoder()
    body = b"\xa1\x07payload"
    bad = frame_packet(body + ((crc16_ccitt_false(body) ^ 1).to_bytes(2, "little")))
    decoder.receive_data(bad + frame(body))
    with pytest.raises(ActuatorProtocolError) as error:
        decoder.next_packet()
    assert error.value.kind == "crc"
    assert decoder.next_packet() == body
    assert decoder.stats.crc_errors == 1


def test_a_too_long_run_without_delimiter_is_one_resync() -> None:
    decoder = FrameDecoder()
    decoder.receive_data(b"\x00" + b"\x07" * (MAX_ENCODED_FRAME_BYTES + 10))
    with pytest.raises(ActuatorProtocolError) as error:
        decoder.next_packet()
    assert error.value.kind == "resync"
    assert decoder.buffered_bytes == 0
    decoder.receive_data(b"\x07" * 500)  # still the same garbage: no second error
    assert decoder.next_packet() is None
    decoder.receive_data(frame(b"\x91\x01ok"))
    packets, errors = drain(decoder)
    assert packets == [b"\x91\x01ok"]
    assert errors == 0
    assert decoder.stats.resyncs == 1


@given(st.lists(st.binary(max_size=3000), max_size=10))
def test_buffer_is_bounded_even_if_nobody_drains(chunks: list[bytes]) -> None:
    decoder = FrameDecoder(max_buffer_bytes=1024)
    for chunk in chunks:
        decoder.receive_data(chunk)
        assert decoder.buffered_bytes <= 1024


def test_overflow_keeps_the_newest_frames() -> None:
    decoder = FrameDecoder(max_buffer_bytes=512)
    frames = [frame(bytes((0x91, i)) + b"x" * 20) for i in range(100)]
    decoder.receive_data(b"".join(frames))
    packets, _ = drain(decoder)
    assert packets, "the newest frames survive"
    assert packets[-1] == bytes((0x91, 99)) + b"x" * 20
    assert decoder.stats.dropped_bytes > 0


@given(st.lists(st.binary(max_size=200), max_size=20))
def test_fuzz_any_bytes_give_packets_or_the_one_error(chunks: list[bytes]) -> None:
    decoder = FrameDecoder()
    for chunk in chunks:
        decoder.receive_data(chunk)
        while True:
            try:
                if decoder.next_packet() is None:
                    break
            except ActuatorProtocolError:
                continue
        assert decoder.buffered_bytes <= MAX_ENCODED_FRAME_BYTES
