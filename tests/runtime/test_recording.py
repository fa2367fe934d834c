"""The flight recorder in the running daemon, and replay of what it wrote.

One daemon run on the built-in "sim" vehicle (its simulated vehicle in its own process,
both scanners streaming) records to a temporary directory while the bench engages,
steps the set speed up and hands back. Then, from the files alone:

- `dbw record check` finds a complete file with every channel replay needs;
- replay through a fresh core rebuilt from the recorded vehicle file and calibration
  reproduces every recorded output exactly, and every request's answer;
- a core with one rule changed (the speed step of the + button) diverges, and the first
  divergence is reported at the right moment: the first + press, with both answers.
"""

from __future__ import annotations

import asyncio
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest
from click.testing import CliRunner

from appliance.cli.record import record as record_group
from appliance.cli.record import replay as replay_command
from appliance.daemon import Daemon, DaemonControlApi
from appliance.modes import Mode
from appliance.recording.channels import CYCLE_TOPIC, REQUEST_TOPIC, RESET_TOPIC
from appliance.recording.reader import RecordingReader, session_files
from appliance.recording.replay import Replayer, core_from_metadata
from tests.runtime.test_daemon_control import isolated_sim_config

pytestmark = pytest.mark.slow

READY_TIMEOUT_S = 30.0
LIVENESS_TIMEOUT_S = 10.0


async def _wait(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    started = time.monotonic()
    while not predicate():
        if time.monotonic() - started > timeout_s:
            pytest.fail(f"{what}: not within {timeout_s} s")
        await asyncio.sleep(0.02)


async def _press_until_accepted(api: DaemonControlApi, name: str) -> None:
    started = time.monotonic()
    while True:
        accepted, message = api.request(name)
        if accepted:
            return
        if time.monotonic() - started > LIVENESS_TIMEOUT_S:
            pytest.fail(f"{name}: refused for {LIVENESS_TIMEOUT_S} s: {message}")
        await asyncio.sleep(0.1)


@pytest.fixture(scope="module")
def recording_dir() -> Iterator[Path]:
    """A daemon run, recorded: engage, + + (speed hold), disengage; its directory."""
    directory = Path(tempfile.mkdtemp(prefix="dbw-rec-", dir="/tmp"))

    async def drive() -> None:
        config = isolated_sim_config()
        config = config.model_copy(
            update={
                "recording": config.recording.model_copy(
                    update={"enabled": True, "directory": str(directory / "recordings")}
                )
            }
        )
        daemon = Daemon(config, control_socket=str(directory / "control.sock"))
        assert daemon.recorder is not None
        api = DaemonControlApi(daemon)
        run = asyncio.ensure_future(daemon.run(handle_signals=False))
        try:
            await _wait(lambda: daemon.core.state.mode is Mode.READY, READY_TIMEOUT_S, "READY")
            await _wait(lambda: not daemon.core.engage_blockers(), LIVENESS_TIMEOUT_S, "engageable")
            await _wait(
                lambda: daemon.recorder is not None and daemon.recorder.status()["running"],
                LIVENESS_TIMEOUT_S,
                "recorder running",
            )
            # A loaded machine may refuse a press (an input late for a moment): press
            # again, as an operator would; the refusals are recorded and replayed too.
            await _press_until_accepted(api, "engage")
            await asyncio.sleep(0.3)
            for _ in range(2):
                await _press_until_accepted(api, "speed_plus")
                await asyncio.sleep(0.3)
            await asyncio.sleep(1.0)
            await _press_until_accepted(api, "disengage")
            await asyncio.sleep(0.5)
        finally:
            daemon.request_stop("test over")
            result = await asyncio.wait_for(run, 10.0)
        assert result.exit_code == 0 and not result.must_force_exit, result

    asyncio.run(drive())
    yield directory
    shutil.rmtree(directory, ignore_errors=True)


def _files(directory: Path) -> list[Path]:
    files = sorted((directory / "recordings").glob("*.mcap"))
    assert files, "the daemon wrote no recording"
    return files


def test_the_file_is_complete_with_every_channel_replay_needs(recording_dir: Path) -> None:
    files = _files(recording_dir)
    result = CliRunner().invoke(record_group, ["check", *map(str, files)])
    assert result.exit_code == 0, result.output
    assert "complete" in result.output
    reader = RecordingReader(files[-1])
    reader.read_all()
    report = reader.report
    assert report.finished and not report.problems
    for topic in (CYCLE_TOPIC, REQUEST_TOPIC, RESET_TOPIC, "/dbw/topic/scan.left", "/log"):
        assert report.per_topic.get(topic, 0) > 0, (topic, report.per_topic)
    assert report.per_topic[REQUEST_TOPIC] >= 4  # engage, + +, disengage (and any refusals)
    assert report.metadata["dbw"]["vehicle"] == "sim"
    assert "toml" in report.metadata["dbw.config"]


def _replay(directory: Path, change: Callable[[Replayer], None] | None = None) -> Replayer:
    files = session_files(_files(directory)[-1])
    first = RecordingReader(files[0])
    messages = first.messages()
    head = next(messages)
    replayer = Replayer(core_from_metadata(first.report.metadata))
    if change is not None:
        change(replayer)
    replayer.handle(head)
    replayer.feed(messages)
    for path in files[1:]:
        replayer.feed(RecordingReader(path).messages())
    return replayer


def test_replay_reproduces_every_output_exactly(recording_dir: Path) -> None:
    result = _replay(recording_dir).result
    assert result.resets >= 1
    assert result.requests >= 4
    assert result.cycles > 100  # a few seconds at 50 Hz
    assert result.divergent_cycles == 0, [d.describe(0) for d in result.divergences]
    assert result.cycles_skipped == 0  # the recorder had the core's first cycle

    cli = CliRunner().invoke(replay_command, [str(_files(recording_dir)[-1]), "--compare"])
    assert cli.exit_code == 0, cli.output
    assert "outputs match the recording exactly" in cli.output


def test_a_changed_rule_is_reported_where_it_first_acts(recording_dir: Path) -> None:
    """The + button's step changed. The first + press locks the speed the vehicle has
    (0 m/s: no step in it), so the second is where the rule first acts: its answer
    differs, and from the next cycle on the set speed (and so the commands) differ."""
    files = _files(recording_dir)
    requests = [
        (m.log_time_ns, m.json())
        for path in files
        for m in RecordingReader(path).messages()
        if m.topic == REQUEST_TOPIC
    ]
    pluses = [ns for ns, data in requests if data["name"] == "speed_plus" and data["accepted"]]
    assert len(pluses) == 2

    def change(replayer: Replayer) -> None:
        core = replayer.core
        core.mode_params = replace(
            core.mode_params, speed_step_mps=core.mode_params.speed_step_mps * 2
        )

    result = _replay(recording_dir, change).result
    assert result.divergent_cycles > 0
    first = result.divergences[0]
    assert first.topic == REQUEST_TOPIC
    assert first.log_time_ns == pluses[1]
    step = isolated_sim_config().engagement.speed_step_mps  # the recorded vehicle's
    assert first.recorded == [True, f"set speed {step:.2f} m/s"]
    assert first.replayed == [True, f"set speed {2 * step:.2f} m/s"]
    cycle_divergences = [d for d in result.divergences if d.topic == CYCLE_TOPIC]
    assert cycle_divergences and cycle_divergences[0].log_time_ns > pluses[1]
