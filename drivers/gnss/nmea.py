"""Sans-I/O NMEA 0183 receiver: bytes from a GNSS/INS port in, typed position events out.

No serial port, clock or asyncio here (STYLE rule 1): the caller feeds whatever a read
returned with `receive_data` and drains `next_event` until it returns None. Timestamping an
event with the time it arrived is the caller's job.

Unlike the LMS111 framer, bad input does not raise: a GNSS stream is a steady flow of
independent one-line sentences, a bad line carries nothing worth stopping for, and what a
supervisor needs is the *rate* of bad lines. So every rejected line is counted by reason in
`counts` (keys are `Reject` members, which are plain strings), and the last one is kept
(truncated) for diagnostics. Nothing on the input side raises, whatever the bytes.

Line rules:

* a line ends at CR or LF (CRLF, LF-only and CR-only all work; empty lines are skipped), and
  a line split across reads is joined;
* bytes before the last ``$`` or ``!`` of a line are garbage: dropped and counted in
  `garbage_bytes` (a port opened mid-sentence starts with a fragment; a lost line end glues
  a fragment to the next sentence). A line with neither is counted as ``no_start``;
* a line longer than `max_line_bytes` (NMEA allows 82 characters; the default leaves room for
  proprietary sentences) is dropped whole, even when its end has not arrived yet, and counted
  once as ``too_long``; a sentence byte outside printable ASCII is ``not_ascii``;
* **the checksum is required.** The spec makes it optional for some talkers, but every GNSS and
  INS receiver this runtime is fitted with sends it, and a serial line to a vehicle roof sees
  noise: a sentence without ``*hh`` is far more likely a damaged one than a legitimate one,
  and a flipped digit in a latitude is a position error of kilometres. So a missing checksum
  is ``no_checksum`` and a wrong one ``checksum``; neither reaches the field parsers;
* sentence types this receiver does not read (GSV, GSA, ZDA, proprietary ``$P...`` and ``!``
  encapsulated sentences) are counted as ``ignored_type``: normal traffic, not errors;
* a verified sentence whose fields cannot be read is ``malformed`` or ``out_of_range`` (see
  `drivers.gnss.sentences`). pynmea2 splits and classifies the sentence; whatever it raises,
  on whatever input, is counted as ``malformed``.

The buffer never holds more than `max_buffer_bytes`: a caller that stops draining loses the
oldest bytes (counted in `overflow_bytes`, and each such cut once as ``overflow``), never
memory.
"""

from __future__ import annotations

import enum
import re
from collections import Counter
from collections.abc import Iterator
from typing import Final

import pynmea2

from drivers.gnss.sentences import SENTENCE_PARSERS, FieldError, NmeaEvent

NMEA_MAX_SENTENCE_CHARS: Final = 82
DEFAULT_MAX_LINE_BYTES: Final = 128
DEFAULT_MAX_BUFFER_BYTES: Final = 64 * 1024
LAST_BAD_LINE_BYTES: Final = 96


class Reject(enum.StrEnum):
    """Why a line produced no event: the keys of `NmeaReceiver.counts`."""

    NO_START = "no_start"
    NOT_ASCII = "not_ascii"
    TOO_LONG = "too_long"
    NO_CHECKSUM = "no_checksum"
    CHECKSUM = "checksum"
    MALFORMED = "malformed"
    OUT_OF_RANGE = "out_of_range"
    OVERFLOW = "overflow"
    IGNORED_TYPE = "ignored_type"


_TERMINATOR = re.compile(rb"[\r\n]")
_PRINTABLE = re.compile(rb"[\x20-\x7e]*")
_FRAME = re.compile(r"(?P<start>[$!])(?P<body>[^*]*)(?:\*(?P<checksum>[0-9A-Fa-f]{2}))?")
_ADDRESS = re.compile(r"(?P<talker>[A-Z0-9]{2})(?P<type>[A-Z0-9]{3})")


def nmea_checksum(body: str) -> int:
    """XOR of the characters between ``$`` (or ``!``) and ``*``, as the two hex digits say."""
    checksum = 0
    for byte in body.encode("ascii"):
        checksum ^= byte
    return checksum


class NmeaReceiver:
    """Bytes in, `NmeaEvent` out; counts what it rejects instead of raising."""

    def __init__(
        self,
        *,
        max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
        max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES,
    ) -> None:
        if max_line_bytes < NMEA_MAX_SENTENCE_CHARS or max_buffer_bytes <= max_line_bytes:
            raise ValueError("need max_line_bytes >= 82 and max_buffer_bytes > max_line_bytes")
        self._max_line_bytes = max_line_bytes
        self._max_buffer_bytes = max_buffer_bytes
        self._buf = bytearray()
        self._discarding = False  # the front of the buffer belongs to a line already rejected
        self._counts: Counter[str] = Counter()
        self._garbage_bytes = 0
        self._overflow_bytes = 0
        self._last_bad_line: bytes | None = None
        self._last_bad_reason: Reject | None = None

    @property
    def counts(self) -> Counter[str]:
        """Lines that produced no event, by `Reject` reason (a copy)."""
        return self._counts.copy()

    @property
    def error_count(self) -> int:
        """Rejected lines except ``ignored_type``: what a supervisor should watch."""
        return sum(n for reason, n in self._counts.items() if reason != Reject.IGNORED_TYPE)

    @property
    def garbage_bytes(self) -> int:
        """Bytes dropped ahead of a ``$``/``!`` or on lines that had neither."""
        return self._garbage_bytes

    @property
    def overflow_bytes(self) -> int:
        """Bytes dropped because the caller fed more than `max_buffer_bytes` without draining."""
        return self._overflow_bytes

    @property
    def last_bad_line(self) -> bytes | None:
        """The start of the most recent rejected line (``ignored_type`` excluded)."""
        return self._last_bad_line

    @property
    def last_bad_reason(self) -> Reject | None:
        return self._last_bad_reason

    @property
    def buffered_bytes(self) -> int:
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes and counters (the port was reopened)."""
        self._buf.clear()
        self._discarding = False
        self._counts.clear()
        self._garbage_bytes = 0
        self._overflow_bytes = 0
        self._last_bad_line = None
        self._last_bad_reason = None

    def receive_data(self, data: bytes) -> None:
        """Append what the port returned. Never raises on content."""
        self._buf += data
        excess = len(self._buf) - self._max_buffer_bytes
        if excess > 0:
            cut_mid_line = self._buf[excess - 1] not in b"\r\n"
            self._reject(Reject.OVERFLOW, self._buf[:excess])
            del self._buf[:excess]
            self._overflow_bytes += excess
            # The line the cut went through lost its start: drop the rest of it too.
            self._discarding = cut_mid_line

    def next_event(self) -> NmeaEvent | None:
        """The next event, or None when the buffered bytes hold no further complete sentence."""
        while True:
            end = _TERMINATOR.search(self._buf)
            if end is None:
                self._check_partial_line()
                return None
            line = bytes(self._buf[: end.start()])
            del self._buf[: end.end()]
            if self._discarding:
                self._discarding = False
                continue
            if not line:
                continue
            if len(line) > self._max_line_bytes:
                self._reject(Reject.TOO_LONG, line)
                continue
            event = self._read_line(line)
            if event is not None:
                return event

    def events(self) -> Iterator[NmeaEvent]:
        """Drain: every event the buffered bytes hold now."""
        while (event := self.next_event()) is not None:
            yield event

    def _check_partial_line(self) -> None:
        """Reject an unfinished line as soon as it is too long, so the buffer stays small."""
        if self._discarding:
            self._buf.clear()
        elif len(self._buf) > self._max_line_bytes:
            self._reject(Reject.TOO_LONG, self._buf)
            self._buf.clear()
            self._discarding = True

    def _reject(self, reason: Reject, line: bytes | bytearray) -> None:
        self._counts[reason] += 1
        if reason is not Reject.IGNORED_TYPE:
            self._last_bad_line = bytes(line[:LAST_BAD_LINE_BYTES])
            self._last_bad_reason = reason

    def _read_line(self, line: bytes) -> NmeaEvent | None:
        # The last start: ``$`` and ``!`` are reserved in NMEA, so one inside a line begins
        # a sentence glued onto a fragment (a byte lost with the line end), worth keeping.
        start = max(line.rfind(b"$"), line.rfind(b"!"))
        if start < 0:
            self._garbage_bytes += len(line)
            self._reject(Reject.NO_START, line)
            return None
        self._garbage_bytes += start
        raw = line[start:]
        if not _PRINTABLE.fullmatch(raw):
            self._reject(Reject.NOT_ASCII, raw)
            return None
        text = raw.decode("ascii")
        frame = _FRAME.fullmatch(text)
        if frame is None:
            self._reject(Reject.MALFORMED, raw)
            return None
        if frame["checksum"] is None:
            self._reject(Reject.NO_CHECKSUM, raw)
            return None
        if int(frame["checksum"], 16) != nmea_checksum(frame["body"]):
            self._reject(Reject.CHECKSUM, raw)
            return None
        if frame["start"] == "!":
            self._reject(Reject.IGNORED_TYPE, raw)
            return None
        try:
            sentence = _split(text, frame["body"])
        except Exception:  # third-party parsing of untrusted bytes: see the module docstring
            self._reject(Reject.MALFORMED, raw)
            return None
        if sentence is None or (parser := SENTENCE_PARSERS.get(sentence[1])) is None:
            self._reject(Reject.IGNORED_TYPE, raw)
            return None
        talker, _, fields = sentence
        try:
            return parser(talker, fields)
        except FieldError as exc:
            self._reject(Reject(exc.reason), raw)
            return None


def _split(text: str, body: str) -> tuple[str, str, list[str]] | None:
    """(talker, sentence type, fields) of a checksum-verified sentence; None if not a talker
    sentence. pynmea2 knows no THS, so for a talker sentence it does not know the address is
    split here (the checksum was verified by the caller, not left to pynmea2)."""
    try:
        parsed = pynmea2.parse(text, check=True)
    except pynmea2.SentenceTypeError:
        address, _, rest = body.partition(",")
        match = _ADDRESS.fullmatch(address)
        if match is None:
            return None
        return match["talker"], match["type"], rest.split(",")
    if not isinstance(parsed, pynmea2.TalkerSentence):
        return None  # proprietary ($P...) or query sentence
    return str(parsed.talker), str(parsed.sentence_type), [str(f) for f in parsed.data]
