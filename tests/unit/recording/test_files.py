"""The recording's file set, driven by made-up log times (the writer reads no clock): split
by size and by duration, the quota, the disk-space stop and resume, write errors and
their retry, and the flush that makes an unfinished file readable.

Every file is read back with `RecordingReader` and compared with what the test wrote."""

from __future__ import annotations

import errno
import itertools
import random
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from appliance.recording import files as files_module
from appliance.recording.files import (
    DISK_CHECK_INTERVAL_NS,
    RETRY_INTERVAL_NS,
    ChannelSpec,
    FileSetParams,
    RecordingFiles,
)
from appliance.recording.reader import RecordingReader

MS = 1_000_000
S = 1_000_000_000
GB = 10**9
METADATA = {
    "dbw": {"session": "20240301T120000Z-4242", "version": "test"},
    "vehicle": {"name": "flatbed", "toml": "[vehicle]\nkind = 'flatbed'\n"},
}
SPEC_A = ChannelSpec("/dbw/topic/a", "dbw.sample:a", b'{"type": "object"}')
SPEC_B = ChannelSpec("/dbw/topic/b", "dbw.sample:b", b'{"type": "object"}')

Written = tuple[str, int, bytes]  # topic, log time, data


class FakeDisk:
    """Free space as the test says; every question is recorded."""

    def __init__(self, free_bytes: int = 100 * GB) -> None:
        self.free_bytes = free_bytes
        self.asked: list[Path] = []

    def __call__(self, path: Path) -> int:
        self.asked.append(path)
        return self.free_bytes


def _params(directory: Path, **changes: Any) -> FileSetParams:
    values: dict[str, Any] = {
        "directory": directory,
        "split_size_bytes": GB,
        "split_duration_ns": 3600 * S,
        "quota_bytes": 100 * GB,
        "warn_free_bytes": 2 * GB,
        "stop_free_bytes": 1 * GB,
        "flush_interval_ns": 100 * MS,
    }
    values.update(changes)
    return FileSetParams(**values)


def _files(
    params: FileSetParams, disk: FakeDisk | None = None, stamp: Callable[[], str] | None = None
) -> RecordingFiles:
    """Files named with one wall-clock stamp (so by their index), unless ``stamp``."""
    return RecordingFiles(
        params, METADATA, stamp or (lambda: "20240301T120000Z"), disk or FakeDisk()
    )


def _advancing_stamp() -> Callable[[], str]:
    """The wall clock moving on between files, as it does on a vehicle."""
    seconds = itertools.count()
    return lambda: f"20240301T12{next(seconds):04d}Z"


def _payloads(seed: int = 1) -> Iterator[bytes]:
    """Messages that do not compress away, so sizes grow as they are written."""
    rng = random.Random(seed)
    k = 0
    while True:
        yield f'{{"k":{k},"noise":"{rng.getrandbits(400):x}"}}'.encode()
        k += 1


def _write(
    files: RecordingFiles, times_ns: list[int], seed: int = 1
) -> tuple[list[Written], list[Written]]:
    """Write one message at each time (two topics in turn): (written, dropped)."""
    written: list[Written] = []
    dropped: list[Written] = []
    payloads = _payloads(seed)
    for i, t in enumerate(times_ns):
        spec = SPEC_A if i % 2 == 0 else SPEC_B
        data = next(payloads)
        accepted = files.write(spec, t, data, i)
        (written if accepted else dropped).append((spec.topic, t, data))
    return written, dropped


def _mcaps(directory: Path) -> list[Path]:
    return sorted(directory.glob("*.mcap"))


def _read(path: Path) -> tuple[RecordingReader, list[Written]]:
    reader = RecordingReader(path)
    messages = [(m.topic, m.log_time_ns, m.data) for m in reader.messages()]
    return reader, messages


def _read_finished(path: Path) -> list[Written]:
    reader, messages = _read(path)
    report = reader.report
    assert report.finished and not report.truncated, (path, report.problems)
    assert report.problems == [] and report.bad_chunks == 0
    assert report.metadata == METADATA
    return messages


# ---- splits --------------------------------------------------------------------------------


def test_split_by_size_gives_whole_files_that_hold_every_message_in_order(
    tmp_path: Path,
) -> None:
    params = _params(tmp_path, split_size_bytes=4000)
    files = _files(params)
    written, dropped = _write(files, [k * 20 * MS for k in range(300)])
    files.close()
    assert dropped == []
    paths = _mcaps(tmp_path)
    assert len(paths) >= 5
    assert files.counts.files_opened == len(paths)
    read = [_read_finished(path) for path in paths]
    assert [m for messages in read for m in messages] == written
    assert all(messages for messages in read)
    # a file is closed at the first message after it reached the size
    for path in paths[:-1]:
        assert path.stat().st_size >= params.split_size_bytes
    assert files.counts.messages == len(written)
    assert files.counts.bytes_written == sum(len(data) for _, _, data in written)


def test_split_by_duration_starts_a_file_at_the_first_message_past_it(tmp_path: Path) -> None:
    params = _params(tmp_path, split_duration_ns=1 * S)
    files = _files(params)
    times = [5 * S + k * 70 * MS for k in range(80)]  # 5.6 s of messages
    written, _ = _write(files, times)
    files.close()
    # each file holds the messages within a second of its first one
    expected: list[list[Written]] = []
    for message in written:
        if not expected or message[1] - expected[-1][0][1] >= 1 * S:
            expected.append([])
        expected[-1].append(message)
    assert [len(group) for group in expected] == [15, 15, 15, 15, 15, 5]
    assert [_read_finished(path) for path in _mcaps(tmp_path)] == expected


def test_every_file_carries_the_metadata_and_each_topic_once_per_file(tmp_path: Path) -> None:
    files = _files(_params(tmp_path, split_duration_ns=1 * S))
    _write(files, [k * 250 * MS for k in range(12)])
    files.close()
    paths = _mcaps(tmp_path)
    assert len(paths) == 3
    for path in paths:
        reader, _ = _read(path)
        assert reader.report.metadata == METADATA
        assert reader.report.per_topic == {SPEC_A.topic: 2, SPEC_B.topic: 2}
        assert reader.report.session == METADATA["dbw"]["session"]


# ---- quota -----------------------------------------------------------------------------------


def test_the_quota_deletes_the_oldest_closed_files(tmp_path: Path) -> None:
    params = _params(tmp_path, split_size_bytes=3000, quota_bytes=10_000)
    files = _files(params, stamp=_advancing_stamp())
    payloads = _payloads()
    opened: list[Path] = []
    sizes: dict[Path, int] = {}
    for i, t in enumerate(k * 20 * MS for k in range(400)):
        assert files.write(SPEC_A, t, next(payloads), i)
        assert files.current_path is not None and files.current_path.exists()
        if not opened or opened[-1] != files.current_path:
            opened.append(files.current_path)
        present = _mcaps(tmp_path)
        sizes.update((p, p.stat().st_size) for p in present)
        # what is left is the newest files, the open one always among them
        assert present == opened[-len(present) :]
        assert sum(sizes[p] for p in present if p != files.current_path) <= params.quota_bytes
    files.close()
    present = _mcaps(tmp_path)
    deleted = opened[: len(opened) - len(present)]
    assert len(deleted) >= 3 and len(present) >= 2
    assert files.counts.files_deleted == len(deleted)
    # the quota is kept, and no file was deleted that it did not need to delete
    total = sum(p.stat().st_size for p in present)
    assert total <= params.quota_bytes < total + sizes[deleted[-1]]


def test_a_quota_smaller_than_a_file_never_deletes_the_open_one(tmp_path: Path) -> None:
    files = _files(_params(tmp_path, split_size_bytes=2000, quota_bytes=1))
    payloads = _payloads()
    written: list[Written] = []
    for i, t in enumerate(k * 50 * MS for k in range(120)):
        data = next(payloads)
        assert files.write(SPEC_A, t, data, i)
        written.append((SPEC_A.topic, t, data))
        assert _mcaps(tmp_path) == [files.current_path]
    assert files.counts.files_opened >= 3
    assert files.counts.files_deleted == files.counts.files_opened - 1
    # the open file holds the latest messages, all but the ones since its last flush
    open_path = files.current_path
    assert open_path is not None
    _, messages = _copy_and_read(open_path, tmp_path / "copy")
    first = written.index(messages[0])
    assert messages == written[first : first + len(messages)]
    assert len(written) - (first + len(messages)) <= 1


# ---- the disk ---------------------------------------------------------------------------------


def test_low_disk_stops_writing_counts_the_drops_and_resumes_above_the_warning(
    tmp_path: Path,
) -> None:
    disk = FakeDisk()
    files = _files(_params(tmp_path), disk)
    assert DISK_CHECK_INTERVAL_NS == 1 * S  # the disk is asked at each whole second here
    times = [k * 100 * MS for k in range(60)]  # 6 s
    written: list[Written] = []
    dropped: list[Written] = []
    for second in range(6):
        # below the stop level at 1 s; between stop and warning at 2 s and 3 s (still
        # stopped: it resumes only above the warning level); back above it at 4 s
        disk.free_bytes = {1: GB - 1, 2: GB + 1, 3: 2 * GB - 1}.get(second, 2 * GB)
        w, d = _write(files, times[second * 10 : second * 10 + 10], seed=second)
        written += w
        dropped += d
        if second in (1, 2, 3):
            assert files.state == "stopped" and "disk low" in files.reason
            assert files.current_path is None
    files.close()
    assert [t for _, t, _ in dropped] == times[10:40]
    assert files.counts.dropped == {"disk_low": 30}
    assert len(disk.asked) == 6 and set(disk.asked) == {tmp_path}
    before, after = _mcaps(tmp_path)
    assert _read_finished(before) == written[:10]  # closed properly when it stopped
    assert _read_finished(after) == written[10:]
    assert [t for _, t, _ in written[10:]] == times[40:]


def test_below_the_warning_level_it_keeps_writing(tmp_path: Path) -> None:
    disk = FakeDisk(free_bytes=GB + 1)
    files = _files(_params(tmp_path), disk)
    written, dropped = _write(files, [k * 300 * MS for k in range(10)])
    files.close()
    assert dropped == [] and files.counts.dropped == {}
    assert [m for p in _mcaps(tmp_path) for m in _read_finished(p)] == written


# ---- write errors -----------------------------------------------------------------------------


class BreakableFile:
    """A file whose writes fail (disk full) while ``broken``: the I/O error a full or
    read-only file system gives, which root in a test would not otherwise see."""

    broken = False

    def __init__(self, path: Path, mode: str) -> None:
        self._file = open(path, mode)  # noqa: SIM115 - closed in close()

    def _check(self) -> None:
        if BreakableFile.broken:
            raise OSError(errno.ENOSPC, "No space left on device")

    def write(self, data: bytes) -> int:
        self._check()
        return self._file.write(data)

    def flush(self) -> None:
        self._check()
        self._file.flush()

    def tell(self) -> int:
        return self._file.tell()

    def close(self) -> None:
        self._file.close()


@pytest.fixture
def breakable(monkeypatch: pytest.MonkeyPatch) -> type[BreakableFile]:
    monkeypatch.setattr(BreakableFile, "broken", False)
    monkeypatch.setattr(files_module, "open", BreakableFile, raising=False)
    return BreakableFile


def test_a_write_error_is_counted_never_raised_and_retried_later(
    tmp_path: Path, breakable: type[BreakableFile]
) -> None:
    files = _files(_params(tmp_path, flush_interval_ns=0))  # every message flushed
    before, _ = _write(files, [k * 100 * MS for k in range(10)])
    breakable.broken = True
    t_fail = 1 * S
    _, failed = _write(files, [t_fail])
    assert files.state == "failed" and "No space left" in files.reason
    assert files.current_path is None
    breakable.broken = False
    # before the retry time everything is dropped, though the disk is fine again
    waiting = [t_fail + k * 500 * MS for k in range(1, 10)]
    assert waiting[-1] < t_fail + RETRY_INTERVAL_NS
    _, dropped = _write(files, waiting)
    files.tick(t_fail + RETRY_INTERVAL_NS - 1)  # ticks neither raise nor reopen
    assert files.current_path is None
    after, still_dropped = _write(files, [t_fail + RETRY_INTERVAL_NS + k * MS for k in range(5)])
    files.close()
    assert len(failed) == 1 and len(dropped) == 9 and still_dropped == []
    assert files.counts.dropped == {"write_error": 10}
    assert files.counts.files_opened == 2
    first, second = _mcaps(tmp_path)
    reader, messages = _read(first)  # abandoned mid-way: read up to its last chunk
    assert not reader.report.finished
    assert messages == before
    assert _read_finished(second) == after


def test_a_directory_that_cannot_be_made_is_a_write_error_until_it_can(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_bytes(b"")
    directory = blocker / "recordings"
    files = _files(_params(directory))
    _, dropped = _write(files, [0, 1 * S])
    assert len(dropped) == 2 and files.state == "failed"
    blocker.unlink()
    _, dropped_again = _write(files, [RETRY_INTERVAL_NS - 1])
    written, none_dropped = _write(files, [RETRY_INTERVAL_NS, RETRY_INTERVAL_NS + 1])
    files.close()
    assert len(dropped_again) == 1 and none_dropped == []
    assert files.counts.dropped == {"write_error": 3}
    assert [m for p in _mcaps(directory) for m in _read_finished(p)] == written


def test_a_flush_error_in_a_tick_is_not_raised_either(
    tmp_path: Path, breakable: type[BreakableFile]
) -> None:
    files = _files(_params(tmp_path))
    _write(files, [0, 10 * MS])
    breakable.broken = True
    files.tick(200 * MS)
    assert files.state == "failed"
    assert not files.write(SPEC_A, 300 * MS, b"{}", 99)
    assert files.counts.dropped == {"write_error": 1}


# ---- flushing ----------------------------------------------------------------------------------


def _copy_and_read(path: Path, into: Path) -> tuple[RecordingReader, list[Written]]:
    into.mkdir(exist_ok=True)
    copy = into / path.name
    shutil.copy(path, copy)
    return _read(copy)


def test_after_a_flush_an_unclosed_file_reads_up_to_it(tmp_path: Path) -> None:
    params = _params(tmp_path / "rec", flush_interval_ns=100 * MS)
    files = _files(params)
    payloads = _payloads()
    written: list[Written] = []
    last_flush_ns = 0  # the file opens at the first message, t = 0
    flushed = 0
    for k in range(40):
        t = k * 30 * MS
        data = next(payloads)
        assert files.write(SPEC_A, t, data, k)
        written.append((SPEC_A.topic, t, data))
        if t - last_flush_ns >= params.flush_interval_ns:
            last_flush_ns, flushed = t, len(written)
        path = files.current_path
        assert path is not None
        reader, messages = _copy_and_read(path, tmp_path / "copies")
        assert not reader.report.finished
        assert reader.report.metadata == METADATA
        # everything up to the last flush, and what is there is a prefix
        assert messages == written[: len(messages)]
        assert len(messages) >= flushed
    # a tick past the interval flushes what is buffered without a new message
    files.tick(40 * 30 * MS + 100 * MS)
    path = files.current_path
    assert path is not None
    _, messages = _copy_and_read(path, tmp_path / "copies")
    assert messages == written
    files.close()
    assert _read_finished(path) == written


def test_names_a_quota_freed_are_not_given_again(tmp_path: Path) -> None:
    """One wall-clock stamp for every file: the names still sort in the order written."""
    params = _params(tmp_path, split_duration_ns=1 * S, quota_bytes=3000)  # about two files
    files = _files(params)
    _write(files, [i * 500 * MS for i in range(8)])  # two messages a file: four files
    files.close()
    names = [p.name for p in _mcaps(tmp_path)]
    # the last two, by their place in the session (the fourth was once named -000)
    assert names == ["dbw-20240301T120000Z-002.mcap", "dbw-20240301T120000Z-003.mcap"]


def test_a_file_deleted_while_open_is_a_write_error_then_a_new_file(tmp_path: Path) -> None:
    files = _files(_params(tmp_path))
    _write(files, [0, 10 * MS])
    first = files.current_path
    assert first is not None
    first.unlink()  # Linux keeps taking writes to the unlinked file: they must not vanish
    assert not files.write(SPEC_A, DISK_CHECK_INTERVAL_NS, b"{}", 2)
    assert files.state == "failed"
    assert files.counts.dropped == {"write_error": 1}
    later = DISK_CHECK_INTERVAL_NS + RETRY_INTERVAL_NS
    assert files.write(SPEC_A, later, b'{"k": 3}', 3)
    files.close()
    (path,) = _mcaps(tmp_path)
    assert path != first
    assert [data for _, _, data in _read_finished(path)] == [b'{"k": 3}']
