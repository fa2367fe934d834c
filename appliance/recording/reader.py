"""Reading a recording, whole or cut short, and saying how much of it is there.

A recording a crash or a power cut ended has no summary and may end inside a record:
it is read front to back (never by its index, which it may not have), each chunk's CRC
checked, and it is used up to the last chunk that is whole. A damaged chunk is reported
and skipped, not trusted; what follows it is still read. `RecordingReader.report` says
what was found: chunks, messages per topic, the time span, whether the file was
finished, and every problem, each in one line.

The records come from `mcap_records`, this project's own reader of the format (its
docstring says why not the mcap library's); `messages(wanted=...)` names the topics to
hand on, and the rest of each chunk is counted but never copied or parsed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from appliance.recording.json_text import loads
from appliance.recording.mcap_records import (
    ChannelRecord,
    ChunkContents,
    ChunkError,
    ChunkRecord,
    FooterRecord,
    McapFileError,
    MessageRecord,
    MetadataRecord,
    SchemaRecord,
    chunk_data,
    new_decompressor,
    read_records,
    split_chunk,
)

# A chunk is a megabyte or so; a length beyond this is damage, not data.
RECORD_SIZE_LIMIT_BYTES = 256 * 1024 * 1024
# What reading can raise besides a record that does not parse: the disk (OSError), and a
# damaged length that asks for more memory than there is.
_READ_ERRORS = (McapFileError, OSError, MemoryError)


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    schema: str
    log_time_ns: int
    sequence: int
    data: bytes

    def json(self) -> Any:
        return loads(self.data)


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
    """Messages of one MCAP file in file order; `report` fills in as they are read.

    ``wanted`` picks topics before anything of a message is decoded or copied: replay
    needs a few of the recording's channels. The report still counts every message."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.report = ReadReport(self.path)
        self._schemas: dict[int, str] = {}
        self._channels: dict[int, tuple[str, str]] = {}  # id: topic, schema name
        self._wanted_ids: set[int] | None = None

    def messages(self, wanted: Callable[[str], bool] | None = None) -> Iterator[RecordedMessage]:
        return self._read(wanted, metadata_only=False)

    def read_all(self) -> list[RecordedMessage]:
        return list(self.messages())

    def read_metadata(self) -> dict[str, dict[str, str]]:
        """The metadata, read up to the first chunk (the recorder writes it before any)."""
        for _ in self._read(None, metadata_only=True):
            pass
        return self.report.metadata

    def _read(
        self, wanted: Callable[[str], bool] | None, metadata_only: bool
    ) -> Iterator[RecordedMessage]:
        report = self.report
        self._wanted_ids = None if wanted is None else set()

        def wants(channel: ChannelRecord) -> bool:
            return wanted is None or wanted(channel.topic)

        try:
            stream = open(self.path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            report.problems.append(f"cannot open: {exc}")
            return
        decompressor = new_decompressor()
        with stream:
            records = read_records(stream, RECORD_SIZE_LIMIT_BYTES)
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    break
                except _READ_ERRORS as exc:
                    report.truncated = True
                    report.problems.append(
                        f"ends after chunk {report.chunks}: {_describe(exc)}; "
                        "read up to the last whole chunk"
                    )
                    break
                if isinstance(record, ChunkRecord):
                    if metadata_only:
                        return
                    try:
                        data = chunk_data(record, decompressor)
                        contents = split_chunk(data, self._wanted_ids, wants)
                    except (ChunkError, MemoryError) as exc:
                        report.bad_chunks += 1
                        report.problems.append(
                            f"chunk {report.chunks + report.bad_chunks} skipped: {_describe(exc)}"
                        )
                        continue
                    report.chunks += 1
                    yield from self._take_chunk(contents, wants)
                elif isinstance(record, MessageRecord):
                    if metadata_only:
                        return
                    wanted_here = self._wanted_ids is None or record.channel_id in self._wanted_ids
                    yield from self._take_chunk(_alone(record, wanted_here), wants)
                elif isinstance(record, MetadataRecord):
                    report.metadata[record.name] = record.metadata
                elif isinstance(record, SchemaRecord | ChannelRecord):
                    self._define(record, wants)
                elif isinstance(record, FooterRecord):
                    report.finished = True

    def _define(
        self, record: SchemaRecord | ChannelRecord, wants: Callable[[ChannelRecord], bool]
    ) -> None:
        if isinstance(record, SchemaRecord):
            self._schemas[record.id] = record.name
            return
        self._channels[record.id] = (record.topic, self._schemas.get(record.schema_id, ""))
        if self._wanted_ids is not None and wants(record):
            self._wanted_ids.add(record.id)

    def _take_chunk(
        self, contents: ChunkContents, wants: Callable[[ChannelRecord], bool]
    ) -> Iterator[RecordedMessage]:
        report = self.report
        channels = self._channels
        for definition in contents.definitions:
            self._define(definition, wants)
        for channel_id, count in contents.count_by_channel.items():
            channel = channels.get(channel_id)
            if channel is None:
                report.problems.append(f"{count} message(s) on unknown channel {channel_id}")
                continue
            report.messages += count
            report.per_topic[channel[0]] = report.per_topic.get(channel[0], 0) + count
        if contents.first_log_time_ns is not None:
            if report.first_log_time_ns is None:
                report.first_log_time_ns = contents.first_log_time_ns
            report.last_log_time_ns = contents.last_log_time_ns
        for channel_id, log_time_ns, sequence, data in contents.messages:
            channel = channels.get(channel_id)
            if channel is not None:
                yield RecordedMessage(channel[0], channel[1], log_time_ns, sequence, data)


def _alone(message: MessageRecord, wanted: bool) -> ChunkContents:
    """A message outside any chunk, taken as a chunk of its own: counted, and handed on
    if it is ``wanted``."""
    return ChunkContents(
        [],
        [message] if wanted else [],
        {message.channel_id: 1},
        message.log_time_ns,
        message.log_time_ns,
    )


def _describe(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def session_files(path: Path) -> list[Path]:
    """The files of ``path``'s recording session in its directory, oldest first, up to and
    including ``path``: replay starts where the daemon started its core."""
    session = read_metadata(path).get("dbw", {}).get("session", "")
    if not session:
        return [path]
    found = []
    for candidate in sorted(path.parent.glob("*.mcap")):
        if candidate.resolve() == path.resolve():
            found.append(path)
            break
        if read_metadata(candidate).get("dbw", {}).get("session", "") == session:
            found.append(candidate)
    return found


def read_metadata(path: Path) -> dict[str, dict[str, str]]:
    """A recording's metadata (its session, vehicle file, calibration), without reading
    its messages; empty for a file that has none or is not a recording."""
    return RecordingReader(path).read_metadata()
