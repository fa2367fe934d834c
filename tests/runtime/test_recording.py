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
import json
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
from appliance.control_client import query
from appliance.daemon import Daemon, DaemonControlApi
from appliance.modes import Mode
from appliance.recording.channels import CYCLE_TOPIC, REQUEST_TOPIC, RESET_TOPIC
from appliance.recording.reader import RecordingReader, read_metadata, session_files
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


async def _engage_and_step_up(daemon: Daemon, api: DaemonControlApi) -> bool:
    """engage, +, + (speed hold at one step); False if the vehicle left it meanwhile."""
    await _wait(lambda: daemon.core.state.mode is Mode.READY, LIVENESS_TIMEOUT_S, "READY")
    await _wait(lambda: not daemon.core.engage_blockers(), LIVENESS_TIMEOUT_S, "engageable")
    for name in ("engage", "speed_plus", "speed_plus"):
        accepted, _ = api.request(name)
        if not accepted:
            api.request("disengage")  # the manual override acknowledges any fault
            return False
        await asyncio.sleep(0.2)
    return daemon.core.state.mode is Mode.SPEED_HOLD


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
            # A calibration maneuver's tap over the whole run: its requests are recorded,
            # and replay taps the same cycles.
            assert api.maneuver("start", "pot-map")[0]
            # A request the socket refuses is an input too: recorded, and changes nothing.
            refused = await query(str(directory / "control.sock"), {"op": "warp"})
            assert refused["ok"] is False
            # A loaded machine may drop the vehicle out of ENGAGED (an input late for a
            # moment): then the operator acknowledges and does it again. The refusals
            # are recorded and replayed like everything else.
            for _ in range(3):
                if await _engage_and_step_up(daemon, api):
                    break
            else:
                pytest.fail("could not engage and step the speed up in three attempts")
            await asyncio.sleep(1.0)
            api.request("disengage")
            await asyncio.sleep(0.5)
            assert api.maneuver("stop", "pot-map")[0]
            (directory / "tapped").write_text(str(daemon.core.maneuver.next_seq))
            await asyncio.sleep(0.2)
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
    assert report.per_topic[REQUEST_TOPIC] >= 4  # engage, + +, disengage (and any retries)
    kinds = [
        json.loads(m.data)
        for path in files
        for m in RecordingReader(path).messages()
        if m.topic == REQUEST_TOPIC
    ]
    refused = [k for k in kinds if k.get("kind") == "bad_request"]
    assert len(refused) == 1 and "unknown op 'warp'" in refused[0]["message"], refused
    assert '"warp"' in refused[0]["name"]
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
    # The maneuver's tap ran again over the same cycles: as many samples as in the run.
    replayer = _replay(recording_dir)
    tapped = int((recording_dir / "tapped").read_text())
    assert replayer.core.maneuver.next_seq == tapped > 50

    cli = CliRunner().invoke(replay_command, [str(_files(recording_dir)[-1]), "--compare"])
    assert cli.exit_code == 0, cli.output
    assert "outputs match the recording exactly" in cli.output


def test_replay_from_the_files_is_the_replay_of_every_message(recording_dir: Path) -> None:
    """`feed_file` takes only the topics replay uses, and comes to the same result, over
    the same time span, as feeding every message."""
    every = _replay(recording_dir).result
    files = session_files(_files(recording_dir)[-1])
    replayer = Replayer(core_from_metadata(read_metadata(files[0])))
    for path in files:
        replayer.feed_file(path)
    assert replayer.result == every


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
    step = isolated_sim_config().engagement.speed_step_mps  # the recorded vehicle's
    stepped = f"set speed {step:.2f} m/s"
    # the first + that stepped the speed (the one before it only locked the speed, 0 m/s)
    first_step_ns = next(
        ns for ns, data in requests if data["name"] == "speed_plus" and data["message"] == stepped
    )

    def change(replayer: Replayer) -> None:
        core = replayer.core
        core.mode_params = replace(
            core.mode_params, speed_step_mps=core.mode_params.speed_step_mps * 2
        )

    result = _replay(recording_dir, change).result
    assert result.divergent_cycles > 0
    first = result.divergences[0]
    assert first.topic == REQUEST_TOPIC
    assert first.log_time_ns == first_step_ns
    assert first.recorded == [True, stepped]
    assert first.replayed == [True, f"set speed {2 * step:.2f} m/s"]
    cycle_divergences = [d for d in result.divergences if d.topic == CYCLE_TOPIC]
    assert cycle_divergences and cycle_divergences[0].log_time_ns > first_step_ns


def test_a_file_cut_short_is_checked_and_replayed_up_to_its_last_whole_chunk(
    recording_dir: Path, tmp_path: Path
) -> None:
    whole = _files(recording_dir)[-1]
    cut = tmp_path / whole.name
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])  # a power cut two thirds of the way in
    check = CliRunner().invoke(record_group, ["check", str(cut)])
    assert check.exit_code == 1, check.output
    assert "cut short" in check.output and "ends after chunk" in check.output
    replayed = CliRunner().invoke(replay_command, [str(cut), "--compare"])
    assert replayed.exit_code == 0, replayed.output  # what is there still matches
    assert "outputs match the recording exactly" in replayed.output
    assert "problem: " in replayed.output  # and it says the file ends early


def test_dump_prints_the_inputs_the_core_saw_at_a_moment(recording_dir: Path) -> None:
    import json

    path = _files(recording_dir)[-1]
    messages = RecordingReader(path).read_all()
    engaged_ns = next(
        m.log_time_ns
        for m in messages
        if m.topic == REQUEST_TOPIC and m.json()["name"] == "engage" and m.json()["accepted"]
    )
    at_s = (engaged_ns - messages[0].log_time_ns) / 1e9 + 0.1
    result = CliRunner().invoke(replay_command, [str(path), "--until", f"{at_s}", "--dump"])
    assert result.exit_code == 0, result.output
    dumped = json.loads(result.output)
    assert at_s <= dumped["at_s"] < at_s + 0.1
    assert dumped["inputs"]["steering"]["pot_raw_counts"] > 0
    assert set(dumped["inputs"]["scans"]) == {"left", "right"}
    assert dumped["output"]["mode"] in {"engaged", "speed_hold", "error"}


def test_replay_of_something_that_is_not_a_recording_is_refused_in_one_line(
    tmp_path: Path,
) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    result = CliRunner().invoke(replay_command, [str(junk)])
    assert result.exit_code == 2
    assert result.output.count("\n") == 1 and "error:" in result.output


def test_record_list_names_the_files_of_the_vehicle(recording_dir: Path, tmp_path: Path) -> None:
    from appliance.cli.record import record as group

    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text(
        'name = "sim"\n[simulation]\nenabled = true\n'
        f'[recording]\ndirectory = "{recording_dir / "recordings"}"\n'
    )
    result = CliRunner().invoke(group, ["list", "--config", str(vehicle)])
    assert result.exit_code == 0, result.output
    for path in _files(recording_dir):
        assert path.name in result.output
    assert "candump" in result.output


def test_a_maneuver_is_fitted_from_the_recording_through_replay(recording_dir: Path) -> None:
    """`dbw calibrate fit RECORDING.mcap`: the tap runs again over the recorded cycles and
    gives the daemon's samples back (as many); this run was no pot-map sweep (the vehicle
    drove), so the fit says why it refuses, and a step not in the recording is named."""
    from appliance.cli.main import cli

    last = str(_files(recording_dir)[-1])
    tapped = int((recording_dir / "tapped").read_text())
    common = ["--config", "sim", "--steering-ratio", "18", "--png", str(recording_dir / "f.png")]
    result = CliRunner().invoke(cli, ["calibrate", "fit", last, *common])
    assert f"the pot-map run replayed, {tapped} samples" in result.output, result.output
    assert result.exit_code == 1 and "REFUSED" in result.output, result.output
    result = CliRunner().invoke(cli, ["calibrate", "fit", last, *common, "--step", "pot-center"])
    assert result.exit_code == 2
    assert "no pot-center maneuver in the recording (maneuvers in it: pot-map)" in result.output
