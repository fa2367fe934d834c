"""The forklift to a pallet through the daemon as shipped: the `forklift-sim` profile (the
`pallet` source, the tablet page on 127.0.0.1, the simulated vehicle in its own process),
a tablet that pairs, selects a pallet from the merged map and holds its button, lets go
on the way (the vehicle stops and waits) and holds again to the end. The truth at the
end comes from the simulated world; the run is recorded, and replaying the recording
through a fresh core gives every output again, the plan's arrival included.
"""

from __future__ import annotations

import asyncio
import math
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from appliance.config import VehicleConfig, load_config
from appliance.core.pallet_autopilot import PalletAutopilot
from appliance.daemon import Daemon, RunResult
from appliance.guidance.pallet_approach import PalletPhase
from appliance.guidance.pallet_final import face_errors
from appliance.guidance.pallet_geometry import nearest_entry_face
from appliance.modes import Mode
from appliance.recording.reader import read_metadata
from appliance.recording.replay import Replayer, core_from_metadata
from appliance.sim.pallet_run import true_pallet
from appliance.sim.site_file import load_site
from drivers.geometry import Pose2D
from tests.browser.test_tablet_page import request
from tests.runtime.inline import isolated
from tests.runtime.shared_machine import for_shared_machine
from tests.runtime.twin_view import TwinView

READY_TIMEOUT_S = 40.0
MERGE_TIMEOUT_S = 30.0
DRIVE_TIMEOUT_S = 90.0  # about 30 s of driving at a walking pace, on a shared machine
BEAT_S = 0.1
# A front-row pallet: a short way, the final straight and the stop (the blind-area
# trials run faster than real time in `dbw sim pallet` and benchmarks/bench_pallet.py).
TARGET = "row_a.r0c1"

pytestmark = [pytest.mark.slow, pytest.mark.timeout(READY_TIMEOUT_S + DRIVE_TIMEOUT_S + 120.0)]


def pallet_config(directory: Path) -> VehicleConfig:
    config = isolated(load_config("forklift-sim"))
    # In line with the target's row, 9 m before it: a plan of about 5 m.
    simulation = config.simulation.model_copy(
        update={"start_x_m": -5.0, "start_y_m": -2.5, "start_yaw_deg": 0.0}
    )
    tablet = config.tablet_page.model_copy(update={"port": 0})
    recording = config.recording.model_copy(
        update={"enabled": True, "directory": str(directory / "recordings")}
    )
    return for_shared_machine(
        config.model_copy(
            update={"simulation": simulation, "tablet_page": tablet, "recording": recording}
        )
    )


async def _until(
    condition: Callable[[], bool], timeout_s: float, daemon: Daemon, what: str
) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pilot = daemon.status_document().get("autopilot")
            mode = daemon.core.state.mode
            pytest.fail(f"{what}: not within {timeout_s} s; mode {mode}; {pilot}")
        await asyncio.sleep(0.02)


class Tablet:
    """A worker's tablet on the page's API: numbered requests, a beat while held."""

    def __init__(self, port: int, token: str) -> None:
        self.port, self.token, self.seq = port, token, 0

    async def post(self, path: str, body: dict[str, object]) -> tuple[int, dict[str, object]]:
        self.seq += 1
        return await request(self.port, path, {**body, "seq": self.seq}, self.token)

    async def hold_while(self, keep: Callable[[], bool], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while keep() and time.monotonic() < deadline:
            status, _ = await self.post("/api/hold", {"held": True})
            assert status == 200
            await asyncio.sleep(BEAT_S)
        assert (await self.post("/api/hold", {"held": False}))[0] == 200


def _phase(source: PalletAutopilot) -> PalletPhase | None:
    return None if source.controller is None else source.controller.phase


@pytest.mark.slow
async def test_the_tablet_guides_the_forklift_to_the_pallet_and_replay_gives_it_again() -> None:
    directory = Path(tempfile.mkdtemp(prefix="dbw-", dir="/tmp"))
    config = pallet_config(directory)
    daemon = Daemon(config, control_socket=str(directory / "control.sock"))
    source = daemon.core.autopilot
    assert isinstance(source, PalletAutopilot) and daemon.tablet is not None
    assert daemon.io.sim_process is not None
    twins = TwinView(daemon.io.sim_process.bench_path)
    run: asyncio.Future[RunResult] = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        await _until(lambda: daemon.core.state.mode is Mode.READY, READY_TIMEOUT_S, daemon, "READY")
        await twins.start()
        page = daemon.tablet.page
        await _until(lambda: page.bound_port is not None, 5.0, daemon, "the page listening")
        assert page.bound_port is not None
        # The code to pair with is on the operator panel's display, until a tablet pairs.
        pairing = daemon.tablet.gate.code
        await _until(lambda: f"PAIR {pairing}" in twins.display_text(), 5.0, daemon, "code")
        code, paired = await request(page.bound_port, "/api/pair", {"code": pairing})
        assert code == 200
        await _until(lambda: "PAIR" not in twins.display_text(), 5.0, daemon, "code gone")
        tablet = Tablet(page.bound_port, str(paired["token"]))
        await _until(lambda: bool(source.names), MERGE_TIMEOUT_S, daemon, "the maps merged")
        status, state = await tablet.post("/api/state", {})
        assert status == 200
        names = {p["name"] for p in state["pallets"]}  # type: ignore[attr-defined,union-attr]
        assert TARGET in names and "row_b.r0c1" in names  # one seen, one behind it
        # A pallet the map does not have: refused, nothing selected.
        status, _ = await tablet.post("/api/select", {"pallet": "row_z.r9c9"})
        assert status != 200 and source.target is None
        status, answer = await tablet.post("/api/select", {"pallet": TARGET})
        assert status == 200, answer
        await _until(lambda: source.controller is not None, 20.0, daemon, "the plan")
        state = (await tablet.post("/api/state", {}))[1]
        assert state["target"] == TARGET and len(state["path"]) > 10  # type: ignore[arg-type]
        # Held until it is on its way, then let go: it stops and waits there.
        await tablet.hold_while(
            lambda: twins.speed_mps() < 0.3 and daemon.core.state.mode is not Mode.ERROR, 30.0
        )
        history = daemon.status_document().get("fault_history", [])
        assert daemon.core.state.mode is not Mode.ERROR, history
        await _until(lambda: abs(twins.speed_mps()) < 0.01, 5.0, daemon, "stopped on release")
        assert _phase(source) is PalletPhase.TO_VIEW
        # Held again: on to the pallet, looked at again, the last straight, the stop.
        await tablet.hold_while(lambda: _phase(source) is not PalletPhase.DONE, DRIVE_TIMEOUT_S)
        assert _phase(source) is PalletPhase.DONE, daemon.status_document().get("autopilot")
        await _until(lambda: abs(twins.speed_mps()) < 0.005, 5.0, daemon, "standing")
        world = (await twins.refresh())["world"]
        truth = Pose2D(world["x_m"], world["y_m"], world["platform_yaw_rad"])
        assert source.plan is not None
        pallet = true_pallet(load_site(config.simulation.site), TARGET)
        face = nearest_entry_face(pallet, source.plan.face.entry_yaw_rad)
        shape = source.shape
        errors = face_errors(
            truth, face, shape.guide_forward_m, shape.tips_forward_m, shape.forks_offset_y_m
        )
        print(
            f"[pallet] tips lateral {1000 * errors.tips_lateral_m:+.1f} mm, along "
            f"{1000 * errors.tips_along_m:+.1f} mm, heading "
            f"{math.degrees(errors.heading_rad):+.3f} deg"
        )
        # Judged on a real-time loop on a shared machine: the 10 mm / 0.3 deg figures
        # are the faster-than-real-time trials' (benchmarks/bench_pallet.py).
        assert abs(errors.tips_lateral_m) < 0.02 and abs(errors.tips_along_m) < 0.03
        assert abs(math.degrees(errors.heading_rad)) < 0.6
        assert not daemon.core.state.faults
    finally:
        await twins.close()
        daemon.request_stop("test over")
        result = await asyncio.wait_for(run, 10.0)
    assert result.exit_code == 0 and not result.must_force_exit, result
    try:
        files = sorted((directory / "recordings").glob("*.mcap"))
        assert files
        replayer = Replayer(core_from_metadata(read_metadata(files[0])))
        for path in files:
            replayer.feed_file(path)
        replayed = replayer.result
        assert replayed.cycles > 1000 and replayed.matched, replayed.divergences[:3]
        pilot = replayer.core.autopilot
        assert isinstance(pilot, PalletAutopilot) and _phase(pilot) is PalletPhase.DONE
    finally:
        shutil.rmtree(directory, ignore_errors=True)
