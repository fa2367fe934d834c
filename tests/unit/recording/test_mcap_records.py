"""The recording reader's own MCAP record reader against the mcap library's, the reference:
the same messages, chunks, damaged chunks, cut and finished files, on files written whole,
cut at every byte and damaged in every byte of their chunks.

The reference is the library's `StreamReader` (chunks emitted whole, CRCs validated) with
each chunk broken up by the library on its own, a chunk that fails skipped and reading
stopped at the first error the stream raises: what `dbw record check` did with it."""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from appliance.recording.reader import RECORD_SIZE_LIMIT_BYTES, RecordingReader
from tests.unit.recording.test_reader import _layout, _write_recording

Written = tuple[str, int, int, bytes]


@dataclass
class Outcome:
    messages: list[Written] = field(default_factory=list)
    chunks: int = 0
    bad_chunks: int = 0
    stopped: bool = False  # the file could not be read to its end
    finished: bool = False
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)


def reference(data: bytes) -> Outcome:
    """What the mcap library reads of ``data``."""
    outcome = Outcome()
    topics: dict[int, str] = {}
    records = StreamReader(
        io.BytesIO(data),
        emit_chunks=True,
        validate_crcs=True,
        record_size_limit=RECORD_SIZE_LIMIT_BYTES,
    ).records
    while True:
        try:
            record = next(records)
        except StopIteration:
            break
        except Exception:
            outcome.stopped = True
            break
        inner: list[Any] = [record]
        if isinstance(record, Chunk):
            try:
                inner = breakup_chunk(record, validate_crc=True)
            except Exception:
                outcome.bad_chunks += 1
                continue
            outcome.chunks += 1
        for item in inner:
            if isinstance(item, Channel):
                topics[item.id] = item.topic
            elif isinstance(item, Message) and item.channel_id in topics:
                outcome.messages.append(
                    (topics[item.channel_id], item.log_time, item.sequence, item.data)
                )
            elif isinstance(item, Metadata):
                outcome.metadata[item.name] = dict(item.metadata)
            elif isinstance(item, Footer):
                outcome.finished = True
            assert not isinstance(item, Schema) or item.name
    return outcome


def ours(data: bytes, path: Path) -> Outcome:
    path.write_bytes(data)
    reader = RecordingReader(path)
    messages = [(m.topic, m.log_time_ns, m.sequence, m.data) for m in reader.messages()]
    report = reader.report
    return Outcome(
        messages,
        report.chunks,
        report.bad_chunks,
        report.truncated,
        report.finished,
        report.metadata,
    )


def _library_written(
    chunked: bool, compression: CompressionType, crcs: bool, data_crc: bool | None = None
) -> bytes:
    """Three channels, one of them registered halfway, written by the library's writer."""
    stream = io.BytesIO()
    writer = Writer(
        stream,
        chunk_size=400,
        compression=compression,
        use_chunking=chunked,
        enable_crcs=crcs,
        enable_data_crcs=crcs if data_crc is None else data_crc,
    )
    writer.start(profile="test", library="test")
    writer.add_metadata("dbw", {"session": "s", "vehicle": "sim"})
    schema = writer.register_schema("dbw.cycle", "jsonschema", b"{}")
    ids = [writer.register_channel(f"/t/{k}", "json", schema) for k in range(2)]
    for k in range(60):
        if k == 30:
            ids.append(writer.register_channel("/t/late", "json", schema))
        payload = json.dumps({"k": k, "x": math.pi * k}).encode()
        writer.add_message(ids[k % len(ids)], log_time=k * 1000, data=payload, publish_time=0)
    writer.finish()
    return stream.getvalue()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    directory = tmp_path_factory.mktemp("recording")
    _write_recording(directory, "s-1", ["20240301T120000Z"], messages=40)
    (path,) = directory.glob("*.mcap")
    return path.read_bytes()


@pytest.mark.parametrize(
    ("chunked", "compression", "crcs"),
    [
        (True, CompressionType.ZSTD, True),
        (True, CompressionType.ZSTD, False),
        (True, CompressionType.NONE, True),
        (False, CompressionType.NONE, True),
    ],
    ids=["zstd", "zstd-no-crc", "uncompressed", "unchunked"],
)
def test_a_whole_file_reads_as_the_library_reads_it(
    tmp_path: Path, chunked: bool, compression: CompressionType, crcs: bool
) -> None:
    data = _library_written(chunked, compression, crcs)
    expected = reference(data)
    assert len(expected.messages) == 60 and expected.finished and not expected.stopped
    assert ours(data, tmp_path / "x.mcap") == expected


def test_a_file_cut_at_any_byte_reads_as_the_library_reads_it(
    recorded: bytes, tmp_path: Path
) -> None:
    path = tmp_path / "cut.mcap"
    for n in range(len(recorded) + 1):
        assert ours(recorded[:n], path) == reference(recorded[:n]), n


def test_a_damaged_chunk_reads_as_the_library_reads_it(recorded: bytes, tmp_path: Path) -> None:
    """Every byte of every chunk's CRC and compressed records flipped. (Its lengths are
    another matter: the library reads a field's length as it comes, past the end of its
    record if it says so, where this reader stops; `test_reader` holds both to never
    reading a message that was not written.)"""
    chunks, _ = _layout(recorded)
    path = tmp_path / "damaged.mcap"
    skipped = 0
    for chunk in chunks:
        crc_at = chunk.start + 9 + 24  # opcode, length; start, end, uncompressed size
        for offset in [*range(crc_at, crc_at + 4), *range(chunk.data_start, chunk.end)]:
            flipped = bytearray(recorded)
            flipped[offset] ^= 0xFF
            expected = reference(bytes(flipped))
            assert ours(bytes(flipped), path) == expected, offset
            skipped += expected.bad_chunks
    assert skipped > sum(c.end - c.data_start for c in chunks) * 9 // 10


@pytest.mark.parametrize("chunk_crcs", [True, False], ids=["chunk-crcs", "data-crc-only"])
def test_the_data_sections_crc_is_checked(tmp_path: Path, chunk_crcs: bool) -> None:
    """A digit of a message in an uncompressed chunk changed (still JSON, another number):
    the chunk's CRC catches it where there is one, and the data section's CRC in the
    DataEnd record in any case, as the library's do."""
    data = _library_written(True, CompressionType.NONE, True)
    if not chunk_crcs:
        data = _library_written(True, CompressionType.NONE, False, data_crc=True)
    at = data.index(b'"x": 3.14')
    flipped = bytearray(data)
    flipped[at + 8] ^= 0x01  # "3.14" to "3.15"
    expected = reference(bytes(flipped))
    assert expected.stopped and expected.bad_chunks == int(chunk_crcs)
    assert ours(bytes(flipped), tmp_path / "x.mcap") == expected


@pytest.mark.parametrize("chunked", [True, False], ids=["chunks", "messages-alone"])
def test_wanted_topics_are_the_same_messages_and_the_same_report(
    recorded: bytes, tmp_path: Path, chunked: bool
) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(recorded if chunked else _library_written(False, CompressionType.NONE, True))
    topic = "/dbw/cycle" if chunked else "/t/late"
    whole = RecordingReader(path)
    everything = whole.read_all()
    picked = RecordingReader(path)
    wanted = list(picked.messages(wanted=lambda name: name == topic))
    assert wanted == [m for m in everything if m.topic == topic] and wanted
    assert picked.report == whole.report
    assert list(RecordingReader(path).messages(wanted=lambda name: False)) == []


def test_read_metadata_opens_no_chunk(recorded: bytes, tmp_path: Path) -> None:
    chunks, _ = _layout(recorded)
    damaged = bytearray(recorded)
    damaged[(chunks[0].data_start + chunks[0].end) // 2] ^= 0xFF  # the first chunk's data
    path = tmp_path / "x.mcap"
    path.write_bytes(bytes(damaged))
    reader = RecordingReader(path)
    assert reader.read_metadata() == {"dbw": {"session": "s-1"}}
    assert reader.report.problems == [] and reader.report.bad_chunks == 0
