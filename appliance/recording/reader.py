"""Reading a recording, whole or cut short, and saying how much of it is there.

A recording a crash or a power cut ended has no summary and may end inside a record:
it is read front to back (never by its index, which it may not have), each chunk's CRC
checked, and it is used up to the last chunk that is whole. A damaged chunk is reported
and skipped, not trusted; what follows it is still read. `RecordingReader.report` says
what was found: chunks, messages per topic, the time span, whether the file was
finished, and every problem, each in one line.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from zstandard import ZstdError

# A chunk is a megabyte or so; a length beyond this is damage, not data.
RECORD_SIZE_LIMIT_BYTES = 256 * 1024 * 1024
# What mcap lets through from a file that ends inside a record (struct.error: a length
# or a number cut short) or whose record is damaged (OverflowError: a length past what
# a read can be asked for).
_RECORD_ERRORS = (
    McapError,
    ValueError,
    EOFError,
    OSError,
    MemoryError,
    OverflowError,
    struct.error,
)
# ... and from a damaged chunk's data (ZstdError: the compressed data does not decompress).
_CHUNK_ERRORS = (*_RECORD_ERRORS, ZstdError)


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    schema: str
    log_time_ns: int
    sequence: int
    data: bytes

    def json(self) -> Any:
        return json.loads(self.data)


@dataclass
class ReadReport:
    path: Path
    chunks: int = 0
    bad_chunks: int = 0
    messages: int = 0
    per_topic: dict[str, int] = field(default_factory=dict)
    first_log_time_ns: int | None = None
    last_log_time_ns: int | None = None
    finished: bool = False  # the file has its footer: it was closed properly
    truncated: bool = False
    problems: list[str] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        if self.first_log_time_ns is None or self.last_log_time_ns is None:
            return 0.0
        return (self.last_log_time_ns - self.first_log_time_ns) / 1e9

    @property
    def session(self) -> str:
        return self.metadata.get("dbw", {}).get("session", "")


class RecordingReader:
    """Messages of one MCAP file in file order; `report` fills in as they are read."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.report = ReadReport(self.path)

    def messages(self) -> Iterator[RecordedMessage]:
        report = self.report
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str]] = {}
        try:
            stream = open(self.path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            report.problems.append(f"cannot open: {exc}")
            return
        with stream:
            reader = StreamReader(
                stream,
                emit_chunks=True,
                validate_crcs=True,
                record_size_limit=RECORD_SIZE_LIMIT_BYTES,
            )
            records = reader.records
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    break
                except _RECORD_ERRORS as exc:
                    report.truncated = True
                    report.problems.append(
                        f"ends after chunk {report.chunks}: {_describe(exc)}; "
                        "read up to the last whole chunk"
                    )
                    break
                if isinstance(record, Chunk):
                    try:
                        inner = breakup_chunk(record, validate_crc=True)
                    except _CHUNK_ERRORS as exc:
                        report.bad_chunks += 1
                        report.problems.append(
                            f"chunk {report.chunks + report.bad_chunks} skipped: {_describe(exc)}"
                        )
                        continue
                    report.chunks += 1
                    for item in inner:
                        message = self._take(item, schemas, channels)
                        if message is not None:
                            yield message
                    continue
                if isinstance(record, Footer):
                    report.finished = True
                message = self._take(record, schemas, channels)
                if message is not None:
                    yield message

    def read_all(self) -> list[RecordedMessage]:
        return list(self.messages())

    def _take(
        self,
        record: Any,
        schemas: dict[int, str],
        channels: dict[int, tuple[str, str]],
    ) -> RecordedMessage | None:
        report = self.report
        if isinstance(record, Schema):
            schemas[record.id] = record.name
        elif isinstance(record, Channel):
            channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
        elif isinstance(record, Metadata):
            report.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                report.problems.append(f"message on unknown channel {record.channel_id}")
                return None
            topic, schema = channel
            report.messages += 1
            report.per_topic[topic] = report.per_topic.get(topic, 0) + 1
            if report.first_log_time_ns is None:
                report.first_log_time_ns = record.log_time
            report.last_log_time_ns = record.log_time
            return RecordedMessage(topic, schema, record.log_time, record.sequence, record.data)
        return None


def _describe(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def session_files(path: Path) -> list[Path]:
    """The files of ``path``'s recording session in its directory, oldest first, up to and
    including ``path``: replay starts where the daemon started its core."""
    target = RecordingReader(path)
    _read_metadata(target)
    session = target.report.session
    if not session:
        return [path]
    found = []
    for candidate in sorted(path.parent.glob("*.mcap")):
        if candidate.resolve() == path.resolve():
            found.append(path)
            break
        reader = RecordingReader(candidate)
        _read_metadata(reader)
        if reader.report.session == session:
            found.append(candidate)
    return found


def _read_metadata(reader: RecordingReader) -> None:
    """Read just far enough to have the metadata (written before any message)."""
    for _ in reader.messages():
        break
