"""MCAP's records read front to back, with only what replay and `dbw record check` use.

Why not the mcap library's `StreamReader`: it reads every field through a stream object
and builds a record object for every message, and replay wants a handful of topics out
of every chunk (the cycles and the scans, not the raw link bytes, the Foxglove copies or
the telemetry samples the cycles already carry); that overhead was most of the time it
took to read a file. Here a chunk is decompressed in one call and walked with
`struct.unpack_from`, and a message is a plain tuple, made only when its channel is
wanted.

What is checked is what the library checks: the magic at both ends, a record length
within a limit, each chunk's CRC of its uncompressed records (where the writer set one),
and the data section's CRC in the DataEnd record (where set). `read_records` raises
`McapFileError` where the file cannot be read on (cut short, not MCAP, damaged framing);
`chunk_data` and `split_chunk` raise `ChunkError` for one chunk that cannot be trusted,
which a reader skips. The tests hold this to the library's own reader.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Container, Iterator
from dataclasses import dataclass
from typing import BinaryIO, NamedTuple

import zstandard

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_METADATA = 0x0C
OP_DATA_END = 0x0F

_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_MESSAGE_HEAD = struct.Struct("<HIQ")  # channel id, sequence, log time (publish time follows)
_MESSAGE_DATA_AT = 22  # the body's bytes before a message's data
_CHUNK_HEAD = struct.Struct("<QQQI")  # start time, end time, uncompressed size, CRC


class McapFileError(Exception):
    """The file cannot be read on from here: cut short, not MCAP, or its framing damaged."""


class ChunkError(Exception):
    """One chunk's records cannot be trusted (they do not decompress or fail their CRC)."""


@dataclass(frozen=True, slots=True)
class SchemaRecord:
    id: int
    name: str


@dataclass(frozen=True, slots=True)
class ChannelRecord:
    id: int
    schema_id: int
    topic: str


@dataclass(frozen=True, slots=True)
class MetadataRecord:
    name: str
    metadata: dict[str, str]


@dataclass(frozen=True, slots=True)
class ChunkRecord:
    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    data: memoryview


@dataclass(frozen=True, slots=True)
class FooterRecord:
    """The file was closed properly: its summary and footer were written."""


class MessageRecord(NamedTuple):
    channel_id: int
    log_time_ns: int
    sequence: int
    data: bytes


Record = SchemaRecord | ChannelRecord | MetadataRecord | ChunkRecord | FooterRecord | MessageRecord


class _Fields:
    """Reads a record's fields in order, never past its body: a length that points
    outside it is damage, not a reason to read the next record as this one's."""

    def __init__(self, body: memoryview) -> None:
        self.body = body
        self.at = 0

    def take(self, size: int) -> memoryview:
        end = self.at + size
        if size < 0 or end > len(self.body):
            raise McapFileError("a field runs past the end of its record")
        field = self.body[self.at : end]
        self.at = end
        return field

    def number(self, fmt: str) -> int:
        value: int = struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0]
        return value

    def text(self) -> str:
        try:
            return str(self.take(self.number("<I")), "utf-8")
        except UnicodeDecodeError as exc:
            raise McapFileError(f"a string field is not UTF-8: {exc}") from exc

    def string_map(self) -> dict[str, str]:
        pairs = _Fields(self.take(self.number("<I")))
        found = {}
        while pairs.at < len(pairs.body):
            key = pairs.text()
            found[key] = pairs.text()
        return found


def read_records(stream: BinaryIO, record_size_limit: int) -> Iterator[Record]:
    """The top-level records of an MCAP stream in file order, up to the footer; a chunk is
    yielded whole (`chunk_data`, `split_chunk`). Raises `McapFileError` where it cannot go
    on; what was yielded before that was read whole (a chunk's records are checked against
    its own CRC by `chunk_data`; the data section's CRC is known only at its end)."""
    if stream.read(len(MAGIC)) != MAGIC:
        raise McapFileError("not an MCAP file (no magic at its start), or cut short there")
    crc: int | None = zlib.crc32(MAGIC)  # of the data section, until its DataEnd record
    while True:
        head = stream.read(_RECORD_HEAD.size)
        if len(head) < _RECORD_HEAD.size:
            raise McapFileError(
                "the file ends before its footer" if not head else "cut short in a record's head"
            )
        opcode, length = _RECORD_HEAD.unpack(head)
        if length > record_size_limit:
            raise McapFileError(f"a record of {length} bytes, over the {record_size_limit} limit")
        body = stream.read(length)
        if len(body) < length:
            raise McapFileError(f"cut short inside a record ({len(body)} of {length} bytes)")
        if opcode == OP_DATA_END:
            if length < 4:
                raise McapFileError("a DataEnd record too short for its CRC")
            expected = struct.unpack_from("<I", body)[0]
            if crc is not None and expected not in (0, crc):
                raise McapFileError(
                    f"the data section's CRC is {crc:#010x}, its DataEnd says {expected:#010x}"
                )
            crc = None
            continue
        if crc is not None:
            crc = zlib.crc32(body, zlib.crc32(head, crc))
        record = _top_level(opcode, memoryview(body))
        if record is not None:
            yield record
        if opcode == OP_FOOTER:
            if stream.read(len(MAGIC)) != MAGIC:
                raise McapFileError("no magic after the footer: cut short, or damaged there")
            return


def _top_level(opcode: int, body: memoryview) -> Record | None:
    fields = _Fields(body)
    if opcode == OP_CHUNK:
        _, _, size, crc = _CHUNK_HEAD.unpack(fields.take(_CHUNK_HEAD.size))
        compression = fields.text()
        return ChunkRecord(size, crc, compression, fields.take(fields.number("<Q")))
    if opcode == OP_MESSAGE:
        if len(body) < _MESSAGE_DATA_AT:
            raise McapFileError("a message record shorter than its header")
        channel_id, sequence, log_time_ns = _MESSAGE_HEAD.unpack_from(body)
        return MessageRecord(channel_id, log_time_ns, sequence, bytes(body[_MESSAGE_DATA_AT:]))
    if opcode == OP_SCHEMA:
        return _schema(fields)
    if opcode == OP_CHANNEL:
        return _channel(fields)
    if opcode == OP_METADATA:
        return MetadataRecord(fields.text(), fields.string_map())
    if opcode == OP_FOOTER:
        return FooterRecord()
    return None  # the header, indexes, statistics, attachments: nothing a reader here uses


def _schema(fields: _Fields) -> SchemaRecord:
    return SchemaRecord(fields.number("<H"), fields.text())


def _channel(fields: _Fields) -> ChannelRecord:
    channel_id, schema_id = fields.number("<H"), fields.number("<H")
    return ChannelRecord(channel_id, schema_id, fields.text())


def new_decompressor() -> zstandard.ZstdDecompressor:
    """One per reader: a context reused for every chunk (it is not for two threads)."""
    return zstandard.ZstdDecompressor()


def chunk_data(chunk: ChunkRecord, decompressor: zstandard.ZstdDecompressor) -> bytes:
    """A chunk's records, uncompressed and checked against its CRC (0: none was written)."""
    if chunk.compression == "zstd":
        try:
            data = decompressor.decompress(chunk.data, max_output_size=chunk.uncompressed_size)
        except (zstandard.ZstdError, MemoryError, OverflowError, ValueError) as exc:
            raise ChunkError(f"does not decompress: {exc}") from exc
    elif chunk.compression == "":
        data = bytes(chunk.data)
    else:
        raise ChunkError(f"compressed with {chunk.compression!r:.40}, which is not read here")
    if chunk.uncompressed_crc != 0:
        crc = zlib.crc32(data)
        if crc != chunk.uncompressed_crc:
            raise ChunkError(f"CRC {crc:#010x} where the chunk says {chunk.uncompressed_crc:#010x}")
    return data


@dataclass
class ChunkContents:
    definitions: list[SchemaRecord | ChannelRecord]
    messages: list[MessageRecord]  # the wanted ones, in file order
    count_by_channel: dict[int, int]  # every message, wanted or not
    first_log_time_ns: int | None = None
    last_log_time_ns: int | None = None


def split_chunk(
    data: bytes, wanted: Container[int] | None, wants: Callable[[ChannelRecord], bool]
) -> ChunkContents:
    """The records of a chunk's ``data``: its schemas and channels, and the messages on the
    channels in ``wanted`` (None: all) or defined here and chosen by ``wants``. Only the
    wanted messages' data is copied out; every message is counted."""
    contents = ChunkContents([], [], {})
    defined_here: set[int] = set()
    messages, counts = contents.messages, contents.count_by_channel
    record_head, message_head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    head_size, data_at = _RECORD_HEAD.size, _MESSAGE_DATA_AT
    first = last = None
    view = memoryview(data)
    at, end = 0, len(data)
    try:
        while at < end:
            opcode, length = record_head(data, at)
            body = at + head_size
            at = body + length
            if at > end:
                raise ChunkError("a record runs past the end of its chunk")
            if opcode == OP_MESSAGE:
                if length < data_at:
                    raise ChunkError("a message record shorter than its header")
                channel_id, sequence, log_time_ns = message_head(data, body)
                if first is None:
                    first = log_time_ns
                last = log_time_ns
                counts[channel_id] = counts.get(channel_id, 0) + 1
                if wanted is None or channel_id in wanted or channel_id in defined_here:
                    message = MessageRecord(
                        channel_id, log_time_ns, sequence, data[body + data_at : at]
                    )
                    messages.append(message)
            elif opcode == OP_CHANNEL:
                channel = _channel(_Fields(view[body:at]))
                contents.definitions.append(channel)
                if wants(channel):
                    defined_here.add(channel.id)
            elif opcode == OP_SCHEMA:
                contents.definitions.append(_schema(_Fields(view[body:at])))
    except struct.error as exc:
        raise ChunkError(f"a record cut short at the end of its chunk: {exc}") from exc
    except McapFileError as exc:  # a field past its record, here inside the chunk
        raise ChunkError(str(exc)) from exc
    contents.first_log_time_ns, contents.last_log_time_ns = first, last
    return contents
