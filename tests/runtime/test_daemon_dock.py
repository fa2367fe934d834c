"""Docking through the daemon as shipped: the `flatbed-sim` profile, the simulated vehicle
in its own process, the `dock` autopilot source, the operator holding the engage button
(hold-to-move) and pressing the throttle pedal through the bench. The truth at the end
comes from the simulated world, not from the daemon's estimate.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import shutil
import tempfile
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from appliance.config import VehicleConfig, load_config
from appliance.daemon import Daemon, RunResult
from appliance.guidance.docking import DockingParams, teeth_inside
from appliance.modes import Mode
from drivers.geometry import Pose2D
from tests.runtime.inline import isolated
from tests.runtime.shared_machine import for_shared_machine
from tests.runtime.twin_view import TwinView

READY_TIMEOUT_S = 40.0
DOCK_TIMEOUT_S = 150.0  # about 45 s of approach from 3 m at walking pace, on a shared machine
# The operator holds the engage button the whole way (hold-to-move): longer than the
# approach may take, or the vehicle stops short where the button was let go.
HOLD_S = DOCK_TIMEOUT_S + 30.0

pytestmark = [pytest.mark.slow, pytest.mark.timeout(READY_TIMEOUT_S + DOCK_TIMEOUT_S + 60.0)]


def dock_config(start_gap_m: float = 3.0, pose_loop: str = "hl") -> VehicleConfig:
    config = isolated(load_config("flatbed-sim"))
    front_forward_m = config.geometry.length_m / 2.0
    simulation = config.simulation.model_copy(
        update={
            "start_x_m": -start_gap_m - front_forward_m,
            "start_y_m": 0.12,
            "start_yaw_deg": 1.0,
        }
    )
    docking = config.docking.model_copy(update={"pose_loop": pose_loop})
    return for_shared_machine(
        config.model_copy(update={"simulation": simulation, "docking": docking})
    )


@contextlib.asynccontextmanager
async def running(config: VehicleConfig) -> AsyncIterator[tuple[Daemon, TwinView]]:
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")
    daemon = Daemon(config, control_socket=str(Path(directory) / "control.sock"))
    assert daemon.io.sim_process is not None
    twins = TwinView(daemon.io.sim_process.bench_path)
    run: asyncio.Future[RunResult] = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        await until(lambda: daemon.core.state.mode is Mode.READY, READY_TIMEOUT_S, daemon, "READY")
        await twins.start()
        yield daemon, twins
    finally:
        await twins.close()
        daemon.request_stop("test over")
        try:
            result = await asyncio.wait_for(run, 5.0)
        finally:
            shutil.rmtree(directory, ignore_errors=True)
    assert result.exit_code == 0 and not result.must_force_exit, result


async def until(
    predicate: object, timeout_s: float, daemon: Daemon, what: str, phases: object = ()
) -> float:
    assert callable(predicate)
    started = time.monotonic()
    while not predicate():
        if time.monotonic() - started > timeout_s:
            doc = daemon.status_document()
            pilot = doc.get("autopilot", {})
            pytest.fail(
                f"{what}: not within {timeout_s} s; autopilot {pilot}; mode {doc.get('mode')}, "
                f"blockers {doc.get('engage_blockers')}, faults {doc.get('faults')}, "
                f"history {doc.get('fault_history', [])[-6:]}, "
                f"last refusal {doc.get('last_refusal')}, phases so far {phases}"
            )
        await asyncio.sleep(0.02)
    return time.monotonic() - started


def docking_status(daemon: Daemon) -> dict[str, object]:
    pilot = daemon.status_document().get("autopilot", {})
    docking = pilot.get("docking", {}) if isinstance(pilot, dict) else {}
    return docking if isinstance(docking, dict) else {}


async def test_the_daemon_docks_the_simulated_flatbed_into_the_troughs() -> None:
    """With the angles from the high level. The other pose loop (the PC104 twin closing
    the loop on the pose and the expected pose the daemon sends it) is driven the same way
    end to end over real CAN in ``tests/hil/test_dock_vcan.py``: run here as well, it
    cost the suite another 47 s for nothing the vcan test leaves out."""
    pose_loop = "hl"
    config = dock_config(pose_loop=pose_loop)
    async with running(config) as (daemon, twins):
        # In the automatic zone with a good pose, the source lets the operator engage.
        await until(lambda: not daemon.core.engage_blockers(), 20.0, daemon, "engageable")
        await twins.act("hold", button="engage", seconds=HOLD_S)
        await until(lambda: daemon.core.state.mode is Mode.ENGAGED, 5.0, daemon, "ENGAGED")
        await twins.act("pedal", pedal="throttle", pct=100.0)
        phases: list[str] = []

        def docked() -> bool:
            phase = str(docking_status(daemon).get("phase", ""))
            if not phases or phases[-1] != phase:
                phases.append(phase)
            return phase == "docked" and abs(twins.speed_mps()) < 0.005

        took_s = await until(docked, DOCK_TIMEOUT_S, daemon, "docked and stopped", phases)
        await twins.act("pedal", pedal="throttle", pct=0.0)
        state = await twins.refresh()
        world = state["world"]
        pose = Pose2D(world["x_m"], world["y_m"], world["platform_yaw_rad"])
        params = DockingParams(front_end_forward_m=config.geometry.length_m / 2.0)
        print(
            f"[dock] {pose_loop}: {took_s:.1f} s, phases {phases}, final pose {pose}, "
            f"status {docking_status(daemon)}"
        )
        assert "approach" in phases and phases[-1] == "docked"
        assert teeth_inside(pose, params), pose
        assert abs(math.degrees(world["platform_yaw_rad"])) < 0.3
        assert daemon.core.state.mode is Mode.ENGAGED  # no fault on the way
