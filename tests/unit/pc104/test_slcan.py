"""SLCAN: the codec against an independent spelling of the Lawicel lines, the line splitter
under any input, and both ends over a real pty (python-can's host, the simulated adapter)."""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.pc104.slcan import (
    MAX_LINE_BYTES,
    LineSplitter,
    SlcanAdapterBus,
    SlcanError,
    SlcanHostBus,
    encode_frame,
    parse_frame,
)

standard_ids = st.integers(0, 0x7FF)
extended_ids = st.integers(0, 0x1FFF_FFFF)
payloads = st.binary(max_size=8)


def reference_line(arbitration_id: int, data: bytes, extended: bool) -> bytes:
    """The Lawicel line spelt out by hand: kind, id digits, dlc digit, two hex digits a byte."""
    kind, width = ("T", 8) if extended else ("t", 3)
    digits = "".join("0123456789ABCDEF"[b >> 4] + "0123456789ABCDEF"[b & 15] for b in data)
    return (kind + format(arbitration_id, f"0{width}X") + str(len(data)) + digits + "\r").encode()


@given(standard_ids, payloads)
def test_standard_frames_encode_as_lawicel_spells_them(arbitration_id: int, data: bytes) -> None:
    line = encode_frame(arbitration_id, data)
    assert line == reference_line(arbitration_id, data, extended=False)
    frame = parse_frame(line[:-1])
    assert (frame.arbitration_id, frame.data, frame.extended, frame.remote) == (
        arbitration_id,
        data,
        False,
        False,
    )
    assert frame.dlc == len(data)


@given(extended_ids, payloads)
def test_extended_frames_round_trip(arbitration_id: int, data: bytes) -> None:
    line = encode_frame(arbitration_id, data, extended=True)
    assert line == reference_line(arbitration_id, data, extended=True)
    frame = parse_frame(line[:-1])
    assert (frame.arbitration_id, frame.data, frame.extended) == (arbitration_id, data, True)


def test_out_of_range_frames_are_refused() -> None:
    with pytest.raises(SlcanError):
        encode_frame(0x800, b"")
    with pytest.raises(SlcanError):
        encode_frame(0x2000_0000, b"", extended=True)
    with pytest.raises(SlcanError):
        encode_frame(0x100, bytes(9))


def test_remote_frames_parse_with_their_dlc() -> None:
    frame = parse_frame(b"r1234")
    assert (frame.arbitration_id, frame.data, frame.remote, frame.dlc) == (0x123, b"", True, 4)


@pytest.mark.parametrize(
    "line",
    [
        b"",
        b"x",
        b"t12",
        b"t1239",
        b"t1232AB",
        b"t123200112",
        b"tG232AABB",
        b"t80000",
        b"T1234",
        b"t+1200",
        b"t1_200",
        b"t1231 A",
    ],
)
def test_malformed_lines_raise_slcan_error(line: bytes) -> None:
    with pytest.raises(SlcanError):
        parse_frame(line)


@given(st.binary(max_size=80))
def test_any_line_parses_or_raises_slcan_error(line: bytes) -> None:
    try:
        frame = parse_frame(line)
    except SlcanError:
        return
    assert 0 <= frame.dlc <= 8 and len(frame.data) in (0, frame.dlc)


@given(st.lists(st.binary(max_size=100), max_size=20), st.integers(1, 50))
def test_splitter_is_bounded_and_independent_of_chunking(
    chunks: list[bytes], chunk_size: int
) -> None:
    stream = b"".join(chunks)
    whole = LineSplitter().feed(stream)
    splitter = LineSplitter()
    pieces = []
    for start in range(0, len(stream), chunk_size):
        pieces += splitter.feed(stream[start : start + chunk_size])
        assert len(splitter._buffer) <= MAX_LINE_BYTES
    assert pieces == whole
    assert all(len(line) <= MAX_LINE_BYTES for line, _ in whole)


def test_an_overlong_line_is_dropped_and_counted_and_the_next_line_survives() -> None:
    splitter = LineSplitter()
    lines = splitter.feed(b"t" * 200 + b"\rt1230\r")
    assert lines == [(b"t1230", 0x0D)]
    assert splitter.dropped_lines == 1


# ---- both ends over a real pty -------------------------------------------------------------


def recv_until(bus: can.BusABC, timeout_s: float = 2.0) -> can.Message:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        message = bus.recv(0.05)
        if message is not None:
            return message
    raise AssertionError("no frame arrived")


@pytest.fixture
def pair(tmp_path: Path):  # type: ignore[no-untyped-def]
    adapter = SlcanAdapterBus(str(tmp_path / "can"))
    host = SlcanHostBus(str(tmp_path / "can"), bitrate=500_000)
    try:
        yield host, adapter
    finally:
        host.shutdown()
        adapter.shutdown()


def test_host_opens_the_adapter_and_frames_cross_both_ways(pair) -> None:  # type: ignore[no-untyped-def]
    host, adapter = pair
    host.send(can.Message(arbitration_id=0x101, data=b"\x01\x02", is_extended_id=False))
    received = recv_until(adapter)
    assert adapter.is_open and adapter.bitrate_code == "S6"
    assert (received.arbitration_id, bytes(received.data)) == (0x101, b"\x01\x02")
    adapter.send(can.Message(arbitration_id=0x201, data=b"\xaa" * 8, is_extended_id=False))
    back = recv_until(host)
    assert (back.arbitration_id, bytes(back.data), back.is_extended_id) == (
        0x201,
        b"\xaa" * 8,
        False,
    )


def test_a_closed_adapter_refuses_frames_and_forwards_nothing(tmp_path: Path) -> None:
    adapter = SlcanAdapterBus(str(tmp_path / "can"))
    try:
        fd = os.open(str(tmp_path / "can"), os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            os.write(fd, b"t1000\r")
            assert adapter.recv(0.2) is None
            assert adapter.frames_refused == 1
            adapter.send(can.Message(arbitration_id=0x200, data=b"", is_extended_id=False))
            time.sleep(0.05)
            assert os.read(fd, 100) == b"\a"  # only the refusal: no frame while closed
        finally:
            os.close(fd)
    finally:
        adapter.shutdown()


def test_a_full_line_drops_whole_frames_never_blocks_and_never_sends_half_a_line(
    pair,  # type: ignore[no-untyped-def]
) -> None:
    host, adapter = pair
    recv_until_open = time.monotonic() + 2.0
    while not adapter.is_open and time.monotonic() < recv_until_open:
        adapter.recv(0.05)
    sent = dropped = 0
    codes: set[int | None] = set()
    started = time.monotonic()
    for _ in range(20_000):  # far more than a pty holds: the adapter is not reading
        try:
            host.send(can.Message(arbitration_id=0x123, data=b"\x55" * 8, is_extended_id=False))
            sent += 1
        except can.CanOperationError as exc:
            codes.add(exc.error_code)
            dropped += 1
    assert time.monotonic() - started < 5.0  # never blocked
    assert dropped > 0 and sent > 0
    assert codes == {errno.ENOBUFS}  # a full buffer, as socketcan reports it: not a lost link
    # Everything the adapter now reads is whole frames: no line was cut short.
    received = 0
    while (message := adapter.recv(0.05)) is not None:
        assert (message.arbitration_id, bytes(message.data)) == (0x123, b"\x55" * 8)
        received += 1
    assert adapter.bad_lines == 0
    assert received >= sent - 1  # the last one may still be on its way out


def test_an_unplugged_adapter_is_a_lost_link_on_the_host(pair) -> None:  # type: ignore[no-untyped-def]
    host, adapter = pair
    adapter.shutdown()
    with pytest.raises(can.CanOperationError) as raised:
        host.recv(0.5)  # the hang-up is readable at once: recv raises, it does not time out
    assert raised.value.error_code == errno.EIO


def test_a_poll_with_nothing_waiting_returns_at_once_whatever_the_port_timeout(
    pair,  # type: ignore[no-untyped-def]
) -> None:
    """recv(0) is the notifier's drain on the event loop: it must never wait for bytes.

    pyserial's read() waits for the port's read timeout (1 ms from python-can, measured
    1.1 ms on every drain); with the timeout set to 5 s here, a read that waits is told
    from one that does not by seconds, not by a tight bound.
    """
    host, adapter = pair
    opened_by = time.monotonic() + 2.0
    while not adapter.is_open and time.monotonic() < opened_by:
        adapter.recv(0.05)  # the adapter reads the host's "open" command
    host.serialPortOrig.timeout = 5.0
    adapter.send(can.Message(arbitration_id=0x201, data=b"\x01", is_extended_id=False))
    assert recv_until(host).arbitration_id == 0x201
    started = time.monotonic()
    for _ in range(3):
        assert host.recv(0) is None
    assert time.monotonic() - started < 2.0
