"""Reading a recording whole, cut short, damaged or not a recording at all: never an
exception, every problem reported, and never a message that was not written.

Where the chunks lie and which messages they hold is read from the file's bytes by a few
lines here (the MCAP record framing, not the mcap library), so what the reader must find
in a file cut at any byte is computed independently of it."""

from __future__ import annotations

import random
import struct
from dataclasses import dataclass
from pathlib import Path

import pytest

from appliance.recording.files import ChannelSpec, FileSetParams, RecordingFiles
from appliance.recording.reader import RecordedMessage, RecordingReader, session_files

MS = 1_000_000
S = 1_000_000_000
MAGIC = b"\x89MCAP0\r\n"
OPCODE_FOOTER = 0x02
OPCODE_CHUNK = 0x06
SPECS = (
    ChannelSpec("/dbw/cycle", "dbw.cycle", b'{"type": "object"}'),
    ChannelSpec("/dbw/topic/gnss", "dbw.sample:GnssPose", b'{"type": "object"}'),
)

Written = tuple[str, int, int, bytes]  # topic, log time, sequence, data


def _write_recording(
    directory: Path,
    session: str,
    stamps: list[str],
    messages: int = 12,
    start_ns: int = 0,
    split_duration_ns: int = 3600 * S,
) -> list[Written]:
    """A recording: one message every 10 ms on two topics, a chunk every 40 ms."""
    params = FileSetParams(
        directory=directory,
        split_size_bytes=10**9,
        split_duration_ns=split_duration_ns,
        quota_bytes=10**12,
        warn_free_bytes=0,
        stop_free_bytes=0,
        flush_interval_ns=40 * MS,
    )
    metadata = {"dbw": {"session": session}} if session else {}
    stamp = iter(stamps)
    files = RecordingFiles(params, metadata, lambda: next(stamp), lambda _: 10**12)
    rng = random.Random(session)
    written: list[Written] = []
    for k in range(messages):
        spec = SPECS[k % 2]
        data = f'{{"k":{k},"x":"{rng.getrandbits(64):x}"}}'.encode()
        t = start_ns + k * 10 * MS
        assert files.write(spec, t, data, 1000 + k)
        written.append((spec.topic, t, 1000 + k, data))
    files.close()
    return written


def _as_written(messages: list[RecordedMessage]) -> list[Written]:
    return [(m.topic, m.log_time_ns, m.sequence, m.data) for m in messages]


@dataclass(frozen=True)
class ChunkSpan:
    start: int  # offset of the record's opcode
    end: int  # offset just past the record
    data_start: int  # where its compressed records begin
    first_log_time_ns: int
    last_log_time_ns: int


def _layout(data: bytes) -> tuple[list[ChunkSpan], int]:
    """The chunks of a whole file, and where its footer record ends (MCAP framing: magic,
    then opcode u8 + length u64 + body per record)."""
    assert data[:8] == MAGIC
    offset, chunks, footer_end = 8, [], -1
    while offset < len(data) - 8:
        opcode, length = struct.unpack_from("<BQ", data, offset)
        body = offset + 9
        if opcode == OPCODE_CHUNK:
            first, last, _size, _crc, name_len = struct.unpack_from("<QQQII", data, body)
            records_at = body + 32 + name_len + 8
            chunks.append(ChunkSpan(offset, body + length, records_at, first, last))
        if opcode == OPCODE_FOOTER:
            footer_end = body + length
        offset = body + length
    assert data[-8:] == MAGIC and footer_end == len(data) - 8
    return chunks, footer_end


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Written]]:
    directory = tmp_path_factory.mktemp("recording")
    written = _write_recording(directory, "s-1", ["20240301T120000Z"])
    (path,) = directory.glob("*.mcap")
    return path, written


def test_a_finished_file_reads_whole_with_no_problems(
    recording: tuple[Path, list[Written]],
) -> None:
    path, written = recording
    reader = RecordingReader(path)
    assert _as_written(reader.read_all()) == written
    report = reader.report
    assert report.finished and not report.truncated
    assert report.problems == [] and report.bad_chunks == 0
    chunks, _ = _layout(path.read_bytes())
    assert report.chunks == len(chunks) == 3
    assert report.messages == len(written)
    assert report.per_topic == {"/dbw/cycle": 6, "/dbw/topic/gnss": 6}
    assert (report.first_log_time_ns, report.last_log_time_ns) == (0, 110 * MS)
    assert report.duration_s == pytest.approx(0.11)
    assert report.metadata == {"dbw": {"session": "s-1"}} and report.session == "s-1"
    assert {m.schema for m in RecordingReader(path).messages()} == {
        "dbw.cycle",
        "dbw.sample:GnssPose",
    }


def test_a_file_cut_at_any_byte_reads_up_to_its_last_whole_chunk(
    recording: tuple[Path, list[Written]], tmp_path: Path
) -> None:
    path, written = recording
    data = path.read_bytes()
    chunks, footer_end = _layout(data)
    cut = tmp_path / "cut.mcap"
    for n in range(len(data) + 1):
        cut.write_bytes(data[:n])
        reader = RecordingReader(cut)
        messages = _as_written(reader.read_all())  # never raises
        whole = [c for c in chunks if c.end <= n]
        last_ns = max((c.last_log_time_ns for c in whole), default=-1)
        expected = [m for m in written if m[1] <= last_ns]
        assert messages == expected, n
        report = reader.report
        assert report.chunks == len(whole), n
        if n < len(data):
            assert report.truncated and report.problems, n
            assert report.problems[-1].startswith(f"ends after chunk {len(whole)}:"), n
        else:
            assert not report.truncated and report.problems == []
        assert report.finished == (n >= footer_end), n


def test_a_damaged_chunk_is_skipped_and_the_others_still_read(
    recording: tuple[Path, list[Written]], tmp_path: Path
) -> None:
    path, written = recording
    data = path.read_bytes()
    chunks, _ = _layout(data)
    middle = chunks[1]
    in_middle = [m for m in written if middle.first_log_time_ns <= m[1] <= middle.last_log_time_ns]
    assert 0 < len(in_middle) < len(written)
    others = [m for m in written if m not in in_middle]
    damaged = tmp_path / "damaged.mcap"
    detected = 0
    for offset in range(middle.data_start, middle.end):
        flipped = bytearray(data)
        flipped[offset] ^= 0xFF
        damaged.write_bytes(bytes(flipped))
        reader = RecordingReader(damaged)
        messages = _as_written(reader.read_all())  # never raises
        report = reader.report
        if report.bad_chunks:
            # the chunk is not trusted; the data section's CRC then fails at its end
            assert report.bad_chunks == 1 and report.chunks == 2, offset
            assert messages == others, offset
            assert report.problems[0].startswith("chunk 2 skipped: "), offset
            detected += 1
        else:  # a byte zstd ignores: the same messages, nothing invented
            assert messages == written, offset
    middle_offset = (middle.data_start + middle.end) // 2
    assert detected >= (middle.end - middle.data_start) * 9 // 10, detected
    flipped = bytearray(data)
    flipped[middle_offset] ^= 0x01
    damaged.write_bytes(bytes(flipped))
    reader = RecordingReader(damaged)
    assert _as_written(reader.read_all()) == others
    assert reader.report.bad_chunks == 1


def test_a_byte_flipped_anywhere_is_reported_and_invents_no_message(
    recording: tuple[Path, list[Written]], tmp_path: Path
) -> None:
    """Lengths, opcodes, CRCs, compression names, the footer: whatever the damage, the
    reader says so or reads the file as written, and raises nothing."""
    path, written = recording
    data = path.read_bytes()
    chunks, _ = _layout(data)
    chunk_bytes = {i for c in chunks for i in range(c.start, c.end)}
    damaged = tmp_path / "damaged.mcap"
    for offset in range(len(data)):
        flipped = bytearray(data)
        flipped[offset] ^= 0xFF
        damaged.write_bytes(bytes(flipped))
        reader = RecordingReader(damaged)
        messages = _as_written(reader.read_all())
        # what is read was written, in the order it was written
        assert messages == [m for m in written if m in messages], offset
        report = reader.report
        if offset in chunk_bytes:
            assert report.problems, offset  # damage to a chunk is never silent
        if not report.problems:  # a file read without a problem was read whole
            assert messages == written and report.finished, offset


@pytest.mark.parametrize(
    "content",
    [b"", b"\x89MCAP0", b"not a recording at all, just text\n", MAGIC + b"\x06" + b"\xff" * 8],
    ids=["empty", "half-magic", "text", "absurd-length"],
)
def test_what_is_not_a_recording_is_a_problem_not_an_exception(
    tmp_path: Path, content: bytes
) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    reader = RecordingReader(path)
    assert reader.read_all() == []
    assert reader.report.problems and reader.report.truncated
    assert not reader.report.finished


def test_a_missing_file_is_a_problem(tmp_path: Path) -> None:
    reader = RecordingReader(tmp_path / "gone.mcap")
    assert reader.read_all() == []
    assert reader.report.problems[0].startswith("cannot open:")


def test_session_files_are_the_earlier_files_of_the_same_session(tmp_path: Path) -> None:
    # two sessions interleaved by name, three files of "a" (one second each), two of "b"
    _write_recording(tmp_path, "a", ["T01", "T03", "T05"], messages=300, split_duration_ns=1 * S)
    _write_recording(tmp_path, "b", ["T02", "T04"], messages=200, split_duration_ns=1 * S)
    _write_recording(tmp_path, "", ["T06"])  # no session: an older recorder's file
    (tmp_path / "dbw-T00-000.mcap").write_bytes(b"junk")  # a damaged file is not one of them
    # a file's index is its place in the session (names sort in the order written)
    a1, a2, a3 = (tmp_path / f"dbw-T0{i}-{n:03d}.mcap" for n, i in enumerate((1, 3, 5)))
    b1, b2 = (tmp_path / f"dbw-T0{i}-{n:03d}.mcap" for n, i in enumerate((2, 4)))
    assert session_files(a3) == [a1, a2, a3]
    assert session_files(a2) == [a1, a2]
    assert session_files(a1) == [a1]
    assert session_files(b2) == [b1, b2]
    no_session = tmp_path / "dbw-T06-000.mcap"
    assert session_files(no_session) == [no_session]
    # an earlier file cut short by a crash still belongs to its session
    a1.write_bytes(a1.read_bytes()[:200])
    assert session_files(a3) == [a1, a2, a3]
