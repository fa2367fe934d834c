"""`dbw calibrate pedals` against the daemon as shipped: the daemon drives the sweep.

The simulated Husky's pedals are shaped as nobody told the fit (a throttle dead band and
a progressive brake, ``[simulation.pedals]``). The vehicle file asks for a short sweep (two
throttle and two brake levels, one speed band) so the test stays short; the full sweep's
figures are measured faster than real time (``benchmarks/bench_calibration.py``). The
operator engages and presses SPEED + through the bench; a brake tap mid-run takes the
pedals back within the cycle, SPEED + resumes, and the interrupted run starts over from
standstill. The maps merged into the calibration file are checked against the simulated
vehicle's own answer to its pedals (``appliance.sim.vehicle.pedal_accel_mps2``).
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest
from click.testing import Result

from appliance.config import VehicleConfig, load_config
from appliance.config.calibration_file import read_calibration_file, write_calibration
from appliance.config.loader import to_toml
from appliance.config.simulated_calibration import simulated_calibration
from appliance.guidance.pedal_sweep import SweepPhase
from appliance.modes import Mode
from appliance.sim.vehicle import VehicleParams, pedal_accel_mps2
from tests.runtime.test_calibrate_steering import dbw, fixed
from tests.runtime.test_daemon_dock import running, until
from tests.runtime.test_daemon_route import route_config

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240.0)]

HIDDEN_PEDALS = {
    "throttle_deadband_pct": 5.0,
    "throttle_exponent": 0.8,
    "brake_deadband_pct": 2.0,
    "brake_exponent": 1.3,
}
SHORT_SWEEP = {
    "top_speed_mps": 1.8,
    "throttle_levels_pct": (30.0, 40.0),
    "brake_levels_pct": (15.0, 25.0),
    "speed_band_edges_mps": (0.5, 1.5),
    "coast_s": 0.5,
    "min_levels_per_band": 2,
}


def sweep_config(tmp_path: Path) -> tuple[VehicleConfig, Path, Path]:
    """The vehicle file (written out: the command reads the same one the daemon runs)
    and a calibration file of its own to merge into."""
    calfile = tmp_path / "calibration.toml"
    base = route_config()
    write_calibration(calfile, simulated_calibration(base.name))
    data = base.model_dump(mode="json")
    data["simulation"]["pedals"] = HIDDEN_PEDALS
    data["pedal_sweep"] |= SHORT_SWEEP
    data["paths"]["calibration_file"] = str(calfile)
    vehicle_file = tmp_path / "husky-pedals.toml"
    vehicle_file.write_text(to_toml(data) + "\n", encoding="utf-8")
    return load_config(vehicle_file), vehicle_file, calfile


def driven_step(
    step: str, vehicle_file: Path, calfile: Path, socket: str, samples: Path
) -> asyncio.Task[Result]:
    """`dbw calibrate STEP` for a step the daemon drives, confirmed, running meanwhile."""
    return asyncio.create_task(
        dbw(
            "calibrate",
            step,
            "--config",
            str(vehicle_file),
            "--calibration",
            str(calfile),
            "--yes",
            "--socket",
            socket,
            "--samples",
            str(samples),
            "--timeout",
            "150",
        )
    )


def phase(daemon: Any) -> SweepPhase | None:
    sweep = daemon.core.programs.last_sweep
    return None if sweep is None or not daemon.core.programs.sweeping else sweep.phase


async def test_the_daemon_sweeps_the_pedals_and_the_fit_finds_the_hidden_ones(
    tmp_path: Path,
) -> None:
    config, vehicle_file, calfile = sweep_config(tmp_path)
    samples = tmp_path / "pedals.jsonl"
    async with running(config) as (daemon, twins):
        socket = str(daemon.control_server.path)
        await until(lambda: fixed(daemon), 10.0, daemon, "a GNSS/INS fix")
        command = driven_step("pedals", vehicle_file, calfile, socket, samples)
        await until(lambda: daemon.core.programs.sweeping or command.done(), 15.0, daemon, "armed")
        assert not command.done(), command.result().output
        assert daemon.core.state.mode is Mode.READY  # armed, but nothing moves yet
        await twins.act("press", button="engage")
        await until(lambda: daemon.core.state.mode is Mode.ENGAGED, 5.0, daemon, "ENGAGED")
        await twins.act("press", button="speed_plus")
        await until(lambda: daemon.core.state.mode is Mode.SPEED_HOLD, 5.0, daemon, "HOLD")
        # Into the first run's throttle, then the operator's foot on the brake.
        await until(
            lambda: (
                phase(daemon) is SweepPhase.THROTTLE
                and (daemon.core.status(0.0)["measured_speed_mps"] or 0.0) > 0.6
            ),
            20.0,
            daemon,
            "the first run under way",
        )
        await twins.act("pedal", pedal="brake", pct=60.0)
        await until(lambda: daemon.core.state.mode is Mode.ENGAGED, 2.0, daemon, "the tap")
        await twins.act("pedal", pedal="brake", pct=0.0)
        await until(lambda: phase(daemon) is SweepPhase.PAUSED, 2.0, daemon, "paused")
        await twins.act("press", button="speed_plus")
        result = await asyncio.wait_for(command, 150.0)
        assert result.exit_code == 0, result.output
        assert "pedals merged" in result.output
        # The sweep ended standing, held on the speed controller at 0 m/s, until the
        # operator takes over.
        assert not daemon.core.programs.sweeping
        assert daemon.core.state.mode is Mode.SPEED_HOLD
        assert daemon.core.state.set_speed_mps == 0.0
        await twins.act("press", button="manual_override")
        await until(lambda: daemon.core.state.mode is Mode.READY, 2.0, daemon, "handed back")

    lines = [json.loads(line) for line in samples.read_text().splitlines()]
    phases = [(s.get("sweep_phase"), s.get("sweep_run")) for s in lines if "sweep_phase" in s]
    paused_at = phases.index(("paused", 0))
    # The interrupted run started over: standing, then its throttle again.
    assert ("stopping", 0) in phases[paused_at:]
    assert ("throttle", 0) in phases[phases.index(("stopping", 0), paused_at) :]

    written = read_calibration_file(calfile, config.name, simulation_enabled=True)
    assert written.pedals is not None and written.items is not None
    assert written.items.pedals is not None and written.items.pedals.accepted
    vehicle = VehicleParams.from_config(config)
    for name, table in (("throttle", written.pedals.throttle), ("brake", written.pedals.brake)):
        top = table.pedal_pct[-1]
        speed = table.speed_mps[0]
        span = abs(
            pedal_accel_mps2(
                vehicle, top if name == "throttle" else 0.0, top if name == "brake" else 0.0, speed
            )
            - pedal_accel_mps2(vehicle, 0.0, 0.0, speed)
        )
        measured = 0
        for level, pct in enumerate(table.pedal_pct):
            for band, band_speed in enumerate(table.speed_mps):
                cell = table.cell(level, band)
                if cell is None:
                    continue
                measured += 1
                throttle, brake = (pct, 0.0) if name == "throttle" else (0.0, pct)
                truth = pedal_accel_mps2(vehicle, throttle, brake, band_speed)
                assert abs(cell - truth) < 0.05 * span, (name, pct, band_speed, cell, truth)
        assert measured >= 2
