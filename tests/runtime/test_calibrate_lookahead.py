"""`dbw calibrate lookahead` against the daemon as shipped: the daemon drives the runs.

The vehicle file asks for a short tuning (one candidate, one run: a line at +1.5 m, short
courses) so the test stays short; the choice among candidates on the paper's
full set of runs is tested faster than real time on the same tuning code
(``tests/unit/maneuvers/test_lookahead_step.py``) and measured in
``benchmarks/bench_lookahead.py``. The operator engages and presses SPEED + through the
bench for each run; an OVERRIDE during the first run's run-up breaks it off, and the same
run is laid again where the vehicle stands and driven to its end. The schedule merged into
the calibration file is the candidate, with the runs' residuals and the servo's baseline;
the flight recording, replayed, gives the same samples and the same choice.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from appliance.cli.main import cli
from appliance.config import VehicleConfig, load_config
from appliance.config.calibration_file import read_calibration_file, write_calibration
from appliance.config.loader import to_toml
from appliance.config.simulated_calibration import simulated_calibration
from appliance.modes import Mode
from tests.runtime.test_calibrate_pedals import driven_step
from tests.runtime.test_calibrate_steering import fixed
from tests.runtime.test_daemon_dock import running, until
from tests.runtime.test_daemon_route import route_config

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240.0)]

SHORT_TUNING = {
    "speeds_mps": (1.5,),
    "conditions": ({"course": "line", "offset_m": 1.5},),
    "offsets_m": (0.5,),
    "gains_s": (0.6,),
    "min_m": 1.5,
    "runup_m": 6.0,
    "test_s": 9.0,
    "stop_m": 5.0,
    "min_scored_s": 5.0,
}


def tuning_config(tmp_path: Path) -> tuple[VehicleConfig, Path, Path]:
    calfile = tmp_path / "calibration.toml"
    base = route_config()
    write_calibration(calfile, simulated_calibration(base.name))
    data = base.model_dump(mode="json")
    data["lookahead_tuning"] |= SHORT_TUNING
    data["paths"]["calibration_file"] = str(calfile)
    data["recording"] |= {"enabled": True, "directory": str(tmp_path / "recordings")}
    vehicle_file = tmp_path / "husky-lookahead.toml"
    vehicle_file.write_text(to_toml(data) + "\n", encoding="utf-8")
    return load_config(vehicle_file), vehicle_file, calfile


def tuning(daemon: Any) -> dict[str, Any]:
    wish = daemon.core.last_wish
    status = {} if wish is None else wish.status.get("tuning")
    return status if isinstance(status, dict) else {}


async def drive_run(daemon: Any, twins: Any, run: int) -> None:
    """Engage when the run is laid, then SPEED + up to its speed (the course caps it)."""
    await until(
        lambda: tuning(daemon).get("run") == run and not daemon.core.engage_blockers(),
        10.0,
        daemon,
        f"run {run} laid",
    )
    await twins.act("press", button="engage")
    await until(lambda: daemon.core.state.mode is Mode.ENGAGED, 5.0, daemon, "ENGAGED")
    for _ in range(12):  # the first press locks the speed, each next one adds a step
        await twins.act("press", button="speed_plus")
        await asyncio.sleep(0.3)
        if (daemon.core.state.set_speed_mps or 0.0) >= 1.5:
            break
    assert (daemon.core.state.set_speed_mps or 0.0) >= 1.5, daemon.core.state


def speed(daemon: Any) -> float:
    return abs(daemon.core.status(0.0)["measured_speed_mps"] or 0.0)


async def take_over(daemon: Any, twins: Any) -> None:
    """OVERRIDE, and the operator's foot on the brake until the vehicle stands."""
    await twins.act("press", button="manual_override")
    await until(lambda: daemon.core.state.mode is Mode.READY, 2.0, daemon, "READY")
    await twins.act("pedal", pedal="brake", pct=40.0)
    await until(lambda: speed(daemon) < 0.02, 10.0, daemon, "standing")
    await twins.act("pedal", pedal="brake", pct=0.0)


async def test_the_daemon_drives_the_runs_and_the_schedule_is_merged(tmp_path: Path) -> None:
    config, vehicle_file, calfile = tuning_config(tmp_path)
    samples = tmp_path / "lookahead.jsonl"
    async with running(config) as (daemon, twins):
        socket = str(daemon.control_server.path)
        await until(lambda: fixed(daemon), 10.0, daemon, "a GNSS/INS fix")
        command = driven_step("lookahead", vehicle_file, calfile, socket, samples)
        await until(lambda: bool(tuning(daemon)) or command.done(), 15.0, daemon, "armed")
        assert not command.done(), command.result().output
        # Run 0, broken off in its run-up: laid again where the vehicle stops.
        await drive_run(daemon, twins, 0)
        await until(lambda: tuning(daemon).get("phase") == "runup", 5.0, daemon, "run-up")
        await take_over(daemon, twins)
        await drive_run(daemon, twins, 0)
        await until(
            lambda: tuning(daemon).get("phase") == "finish" and speed(daemon) < 0.02,
            40.0,
            daemon,
            "the run stopped at its end",
        )
        await take_over(daemon, twins)
        result = await asyncio.wait_for(command, 60.0)
        assert result.exit_code == 0, result.output
        assert "lookahead merged" in result.output, result.output
        assert daemon.core.autopilot.tuning is None

    lines = [json.loads(line) for line in samples.read_text().splitlines()]
    phases = [(s.get("tune_phase"), s.get("tune_run")) for s in lines if "tune_phase" in s]
    first_runup = phases.index(("runup", 0))
    assert ("stand", 0) in phases[first_runup:]  # broken off, and run 0 again
    assert ("finish", 0) in phases and phases[-1] == ("done", None)

    # The flight recording gives the same samples back (replay runs the tap and the runs
    # again over the recorded cycles), and the same choice.
    recording = sorted((tmp_path / "recordings").glob("*.mcap"))[-1]
    replayed = CliRunner().invoke(
        cli, ["calibrate", "fit", str(recording), "--config", str(vehicle_file), "--json"]
    )
    assert replayed.exit_code == 0, replayed.output
    figures = json.loads(next(x for x in replayed.output.splitlines() if x.startswith("{")))
    assert figures["chosen"] == {"offset_m": 0.5, "gain_s": 0.6, "min_m": 1.5}, figures
    taken = sum(1 for line in lines if "seq" in line)
    assert f"the lookahead run replayed, {taken} samples" in replayed.output, replayed.output

    written = read_calibration_file(calfile, config.name, simulation_enabled=True)
    assert written.guidance is not None and written.guidance.look_ahead is not None
    assert written.guidance.look_ahead.gain_s == 0.6
    assert written.guidance.servo_torque is not None
    assert written.items is not None and written.items.lookahead is not None
    record = written.items.lookahead
    assert record.accepted and record.residual_max < 0.3 and "aborted" not in record.rejected
