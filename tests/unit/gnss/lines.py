"""Test helpers: sentences with checksums computed here, not by the code under test."""

from __future__ import annotations

import functools
import operator

from drivers.gnss import NmeaEvent, NmeaReceiver


def xor_checksum(body: str) -> int:
    """NMEA checksum, written independently of `drivers.gnss.nmea.nmea_checksum`."""
    return functools.reduce(operator.xor, body.encode("ascii"), 0)


def sentence(body: str, *, start: str = "$", eol: bytes = b"\r\n") -> bytes:
    """``$`` + body + ``*hh`` + end of line, the way a receiver sends it."""
    return f"{start}{body}*{xor_checksum(body):02X}".encode("ascii") + eol


def feed(receiver: NmeaReceiver, chunks: list[bytes]) -> list[NmeaEvent]:
    """Feed chunk by chunk, draining after each, as the serial loop will."""
    out: list[NmeaEvent] = []
    for chunk in chunks:
        receiver.receive_data(chunk)
        out += receiver.events()
    return out


def parse_all(data: bytes) -> tuple[list[NmeaEvent], NmeaReceiver]:
    receiver = NmeaReceiver()
    return feed(receiver, [data]), receiver


def parse_one(body: str) -> NmeaEvent:
    """The single event one sentence gives; fails with the receiver's counts otherwise."""
    events, receiver = parse_all(sentence(body))
    assert len(events) == 1, (receiver.counts, receiver.last_bad_line)
    return events[0]


def reject_reason(body: str) -> str:
    """The one reason a well-framed sentence with this body was rejected."""
    events, receiver = parse_all(sentence(body))
    assert events == []
    [(reason, count)] = receiver.counts.items()
    assert count == 1
    return reason
