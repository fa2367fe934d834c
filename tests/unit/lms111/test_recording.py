"""Recording the twin's TCP stream and replaying it through the core."""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest

from appliance.sim import Pose2D, load_site
from appliance.sim.twins.lms111 import Lms111Twin, TwinFaults
from drivers.lms111 import Dialect, Scan
from drivers.lms111.recording import (
    RECORD_HEADER,
    RecordingError,
    RecordingTruncated,
    RecordingWriter,
    RecordStats,
    ReplayError,
    iter_chunks,
    iter_recording,
    read_header,
    record,
    scan_line,
    scan_summary,
    summarize_recording,
)


@pytest.fixture
async def twin(request: pytest.FixtureRequest) -> AsyncIterator[Lms111Twin]:
    dialect, faults = getattr(request, "param", (Dialect.COLA_A, None))
    twin = Lms111Twin(
        load_site("launcher"),
        Pose2D(4.5, 1.1, math.radians(45.0)),
        lambda _: Pose2D(-10.0, 0.3, 0.0),
        dialect=dialect,
        faults=faults,
    )
    await twin.start()
    yield twin
    await twin.stop()


@pytest.mark.parametrize(
    "twin", [(d, None) for d in Dialect], indirect=True, ids=[d.value for d in Dialect]
)
async def test_record_then_replay_gives_back_every_scan(twin: Lms111Twin, tmp_path: Path) -> None:
    path = tmp_path / "left.lms111rec"
    dialect = twin.device.dialect
    stats = await record("127.0.0.1", twin.port, path, 1.0, dialect, scan_frequency_hz=25)
    assert stats.scans == pytest.approx(25, abs=3)
    assert stats.malformed_telegrams == 0 and stats.chunks > 0
    header_line = path.read_bytes().split(b"\n", 1)[0] + b"\n"
    assert path.stat().st_size == len(header_line) + stats.chunks * RECORD_HEADER.size + stats.bytes

    header = read_header(path)
    assert (header.host, header.port, header.dialect) == ("127.0.0.1", twin.port, dialect)
    assert header.metadata["scan_frequency_hz"] == 25

    replayed = list(iter_recording(path))
    scans = [e for e in replayed if isinstance(e, Scan)]
    assert not [e for e in replayed if isinstance(e, ReplayError)]
    assert len(scans) == stats.scans
    counters = [s.scan_counter for s in scans]
    assert (counters[0], counters[-1]) == (stats.first_scan_counter, stats.last_scan_counter)
    assert np.all(np.diff(counters) == 1)
    assert all(s.scan_frequency_hz == 25 and s.host_receive_time_s is not None for s in scans)
    times = [s.host_receive_time_s or 0.0 for s in scans]
    assert times == sorted(times)

    summary = summarize_recording(path)
    assert (summary.scans, summary.errors) == (stats.scans, 0)
    assert summary.dropped_scans <= twin.stats.scans_skipped  # only the twin's own skips
    assert summary.truncated is None and 0.8 < summary.duration_s < 1.2
    json.dumps(summary.to_dict())
    line = json.dumps(scan_summary(scans[0]))
    assert '"beams": 541' in line
    assert "541 beams" in scan_line(scans[0])


async def record_until_corrupted(twin: Lms111Twin, path: Path, corrupted: int) -> RecordStats:
    """Record until the twin has sent ``corrupted`` bad scans, then 1 s of good ones.

    Not a fixed window: on a loaded machine the twin skips scans (they are gaps, not
    corruptions), so a fixed time holds no known number of bad ones. Once the twin has
    sent enough it stops corrupting, and the recorder's clock is moved on so that the
    recording ends 1 s later: every bad scan is in the file by then, followed by good ones
    (so a CoLa-A truncation is exposed by the next start marker). The receive times after
    that point carry the clock's jump.
    """
    budget_s, after_s = 30.0, 1.0
    offset_s = 0.0

    def clock() -> float:
        return time.monotonic() + offset_s

    async def stop_corrupting_when_enough() -> None:
        nonlocal offset_s
        while twin.stats.corrupted < corrupted:
            await asyncio.sleep(0.005)
        twin.faults.corrupt_every = 0
        # the deadline (at least budget_s after started_s) is now after_s away
        offset_s = budget_s - after_s - (time.monotonic() - started_s)

    started_s = time.monotonic()
    watcher = asyncio.create_task(stop_corrupting_when_enough())
    try:
        return await record(
            "127.0.0.1", twin.port, path, budget_s, twin.device.dialect, clock=clock
        )
    finally:
        watcher.cancel()


@pytest.mark.parametrize(
    "twin",
    [(Dialect.COLA_B, TwinFaults(corrupt_every=5)), (Dialect.COLA_A, TwinFaults(corrupt_every=5))],
    indirect=True,
    ids=["CoLa-B-checksums", "CoLa-A-truncations"],
)
async def test_a_misbehaving_scanner_replays_with_its_errors(
    twin: Lms111Twin, tmp_path: Path
) -> None:
    path = tmp_path / "bad.lms111rec"
    stats = await record_until_corrupted(twin, path, 4)
    events: list[Scan | ReplayError] = []
    summary = summarize_recording(path, events.append)
    assert summary.errors == stats.malformed_telegrams == twin.stats.corrupted >= 4
    assert summary.scans == stats.scans
    # Each corrupted scan between two good ones is a counter gap; one before the first good
    # scan (the recording started next to it) is not. The twin may also skip scans itself
    # under load.
    good = [i for i, event in enumerate(events) if isinstance(event, Scan)]
    between = [e for e in events[good[0] : good[-1]] if isinstance(e, ReplayError)]
    assert len(between) >= summary.errors - 1
    assert len(between) <= summary.dropped_scans <= len(between) + twin.stats.scans_skipped


async def test_a_truncated_recording_is_reported_after_its_complete_records(
    twin: Lms111Twin, tmp_path: Path
) -> None:
    path = tmp_path / "cut.lms111rec"
    stats = await record("127.0.0.1", twin.port, path, 0.3)
    data = path.read_bytes()
    path.write_bytes(data[:-7])
    replayed: list[Scan | ReplayError] = []
    with pytest.raises(RecordingTruncated, match=r"truncated at byte \d+: the record says"):
        replayed.extend(iter_recording(path))
    assert all(isinstance(event, Scan) for event in replayed)
    assert stats.scans - 2 <= len(replayed) <= stats.scans
    summary = summarize_recording(path)
    assert summary.truncated is not None and "complete records" in summary.truncated

    path.write_bytes(data)
    *_, (_, _, last_offset) = iter_chunks(path)
    path.write_bytes(data[: last_offset + 5])  # cut inside the last record's header
    with pytest.raises(RecordingTruncated, match="record header needs 12 bytes, 5 present"):
        list(iter_recording(path))


def test_a_file_that_is_not_a_recording_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_bytes(b"hello\n")
    with pytest.raises(RecordingError, match="is not an LMS111 recording"):
        list(iter_recording(path))
    with RecordingWriter(tmp_path / "empty.rec", {"host": "h", "port": 1, "dialect": "CoLa-A"}):
        pass
    assert list(iter_recording(tmp_path / "empty.rec")) == []
