"""The recorder under the issue's load loses nothing it does not count.

A real recorder process is fed, through the daemon-side tap, what a flat-bed produces at
full rate: both scanners at 50 Hz, the PC104's decoded frames at 4,000 per second, the
four boards at 100 Hz, and a control cycle every 20 ms (inputs and output of a real
core). Afterwards every message the tap generated is either in the file or counted as
dropped (in the daemon for a full pipe, in the recorder for the disk): the file holds
exactly what was sent, in order, per topic. The run also goes through the pipe's
back-pressure path with a backlog bound small enough to hit, and the same accounting must
hold there.
"""

from __future__ import annotations

import asyncio
import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from appliance.config import load_config
from appliance.core.core import ControlCore
from appliance.core.inputs import ControlInputs
from appliance.recording.channels import CYCLE_TOPIC, SAMPLE_TOPIC_PREFIX
from appliance.recording.reader import RecordingReader
from appliance.recording.service import Recorder
from appliance.topics import TopicRegistry
from drivers.actuators.messages import BoardStatus, FaultCode, SteeringTelemetry
from drivers.geometry import Pose2D
from drivers.lms111.mounted import MountedScan
from drivers.lms111.scan import scan_from_ranges
from drivers.pc104.messages import ControlSource, MotionPattern, Pc104Status

pytestmark = pytest.mark.slow

SECONDS = 3.0
TICK_S = 0.01


class _Ctx:
    name = "recorder"

    def beat(self) -> None:
        pass


def _scan(side: str, t_s: float, rng: np.random.Generator) -> MountedScan:
    ranges = rng.uniform(0.5, 20.0, 1081)
    return MountedScan(
        scan_from_ranges(ranges, angular_step_deg=0.25), side, Pose2D(0.0, 0.0, 0.0), t_s, 0
    )


async def _drive(recorder: Recorder, topics: TopicRegistry) -> Counter[str]:
    """Publish the load for SECONDS; what was generated, per recorded topic."""
    rng = np.random.default_rng(7)
    core = ControlCore(load_config("flatbed"), None)
    generated: Counter[str] = Counter()
    steering = SteeringTelemetry(BoardStatus(0), FaultCode(0), 0, 0.0, 0.0, 0.0, 2048, 24.0)
    status = Pc104Status(MotionPattern.STOP, True, ControlSource.AUTOMATIC)
    loop = asyncio.get_running_loop()
    start_s = loop.time()
    while (now_s := loop.time()) - start_s < SECONDS:
        # Catch up to the rates by elapsed time (a sleep oversleeps on a busy machine).
        elapsed_s = now_s - start_s
        while generated["board.steering"] < elapsed_s * 100.0:
            for name in ("board.steering", "board.throttle", "board.brake", "board.panel"):
                topics.get(name).publish(steering, now_s)  # the type does not matter here
                generated[name] += 1
        while generated["pc104.status"] < elapsed_s * 4000.0:
            topics.get("pc104.status").publish(status, now_s)
            generated["pc104.status"] += 1
        while generated["cycle"] < elapsed_s * 50.0:
            scans = {}
            for side in ("left", "right"):
                scans[side] = _scan(side, now_s, rng)
                topics.get(f"scan.{side}").publish(scans[side], now_s)
                generated[f"scan.{side}"] += 1
            inputs = ControlInputs(ages_s={"board.steering": 0.001, "x": math.inf}, scans=scans)
            recorder.on_cycle(now_s, inputs, core.step(inputs, now_s))
            generated["cycle"] += 1
        await asyncio.sleep(TICK_S)
    return generated


async def _record(directory: Path, max_backlog_mb: float) -> tuple[Counter[str], Recorder]:
    config = load_config("flatbed")
    config = config.model_copy(
        update={
            "recording": config.recording.model_copy(
                update={
                    "directory": str(directory),
                    "max_backlog_mb": max_backlog_mb,
                    "warn_free_mb": 0.0,
                    "stop_free_mb": 0.0,
                }
            )
        }
    )
    topics = TopicRegistry()
    for name in (
        "board.steering",
        "board.throttle",
        "board.brake",
        "board.panel",
        "pc104.status",
        "scan.left",
        "scan.right",
    ):
        topics.get(name)
    recorder = Recorder(config, "")
    recorder.attach(topics)
    service = asyncio.ensure_future(recorder.run(_Ctx()))  # type: ignore[arg-type]
    try:
        for _ in range(500):
            if recorder.status()["running"]:
                break
            await asyncio.sleep(0.01)
        generated = await _drive(recorder, topics)
        # The recorder's process finishes its file (a loaded machine takes its time).
        assert await recorder.close(timeout_s=60.0), "the recorder did not finish its file"
    finally:
        service.cancel()
        with_result: Any = await asyncio.gather(service, return_exceptions=True)
        assert with_result
    return generated, recorder


def _in_file(directory: Path) -> Counter[str]:
    found: Counter[str] = Counter()
    for path in sorted(directory.glob("*.mcap")):
        reader = RecordingReader(path)
        last_seq: dict[str, int] = {}
        for message in reader.messages():
            if message.topic == CYCLE_TOPIC:
                found["cycle"] += 1
            elif message.topic.startswith(SAMPLE_TOPIC_PREFIX):
                topic = message.topic.removeprefix(SAMPLE_TOPIC_PREFIX)
                seq = message.json()["seq"]
                assert seq > last_seq.get(topic, 0), (topic, seq)  # in order, no repeats
                last_seq[topic] = seq
                found[topic] += 1
        assert reader.report.finished and not reader.report.problems, reader.report.problems
    return found


def _dropped(recorder: Recorder) -> Counter[str]:
    status = recorder.status()
    dropped = Counter(status["dropped"])
    assert not dropped, f"the recorder dropped on a roomy disk: {dropped}"
    return Counter(status["dropped_in_daemon"])


def test_at_full_load_everything_is_recorded_or_counted(tmp_path: Path) -> None:
    generated, recorder = asyncio.run(_record(tmp_path, max_backlog_mb=16.0))
    found = _in_file(tmp_path)
    dropped_samples = _dropped(recorder)
    assert generated["pc104.status"] >= 0.98 * 4000 * SECONDS  # the load was there
    for topic, count in generated.items():
        kind = "cycle" if topic == "cycle" else "sample"
        assert found[topic] <= count
        if dropped_samples[kind] == 0:
            assert found[topic] == count, (topic, found[topic], count)
    lost = sum(generated.values()) - sum(found.values())
    assert lost == sum(dropped_samples[k] for k in ("cycle", "sample")), (lost, dropped_samples)


def test_a_full_pipe_drops_and_counts_never_blocks(tmp_path: Path) -> None:
    """A backlog bound of 1 kB: most messages cannot be queued; each is counted."""
    generated, recorder = asyncio.run(_record(tmp_path, max_backlog_mb=0.001))
    found = _in_file(tmp_path)
    dropped = _dropped(recorder)
    assert dropped["sample"] + dropped["cycle"] > 0
    lost = sum(generated.values()) - sum(found.values())
    assert lost == dropped["sample"] + dropped["cycle"], (lost, dropped)
