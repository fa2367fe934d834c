"""The `pallet` source standing in the simulated `pallets` site (its scans rendered there,
the scanners calibrated): it localizes on the posts, merges the worker's map once it
stands localized, refuses what it cannot do in words, plans a selected pallet in the
background and plans again when the vehicle was moved before it engaged. Driving it is
`dbw sim pallet`'s (tests/unit/sim) and the daemon's (tests/runtime/test_pallet_daemon)."""

from __future__ import annotations

import math
from functools import cache
from pathlib import Path

import pytest

from appliance.config import load_config
from appliance.config.models import VehicleConfig
from appliance.core.core import ControlCore
from appliance.core.jobs import InlineJobs
from appliance.core.pallet_autopilot import PalletAutopilot
from appliance.core.pallet_parts import load_worker_map
from appliance.core.wish import AutopilotWish, Observation
from appliance.mapping.map_file import MapFileError
from appliance.sim.pallet_run import _mounted, _Scanners
from appliance.sim.site_file import load_site
from drivers.geometry import Pose2D
from drivers.lms111.mounted import MountedScan

START = Pose2D(-5.0, -2.5, 0.0)


@cache
def _config() -> VehicleConfig:
    return load_config("forklift-sim")


@cache
def _scanners() -> _Scanners:
    config = _config()
    return _Scanners(config, load_site(config.simulation.site), 1)


def _source(config: VehicleConfig | None = None) -> PalletAutopilot:
    return PalletAutopilot(config or _config(), jobs=InlineJobs(), scanners=_scanners().setups)


class Standing:
    """Steps a source at 50 Hz with the vehicle standing at ``pose``, scans at 25 Hz."""

    def __init__(self, source: PalletAutopilot) -> None:
        self.source, self.t_s = source, 0.0
        self.scans: dict[str, MountedScan | None] = {"left": None, "right": None}

    def run(self, seconds: float, pose: Pose2D = START, speed_mps: float = 0.0) -> AutopilotWish:
        """``speed_mps``: driven by hand straight ahead from ``pose`` meanwhile."""
        scanners = _scanners()
        wish = AutopilotWish(ready=False)
        self.pose = pose
        for _ in range(round(seconds * 50)):
            pose = self.pose = self.pose.compose(Pose2D(speed_mps * 0.02, 0.0, 0.0))
            k = round(self.t_s * 50)
            if k % 2 == 0:
                for name in ("left", "right"):
                    ranges = scanners.render(name, self.t_s, pose)
                    self.scans[name] = _mounted(scanners, name, ranges, self.t_s)
            observation = Observation(
                self.t_s, speed_mps, 0.0, dict(self.scans), False, jobs_done=self.source.jobs.done()
            )
            wish = self.source.update(observation)
            self.t_s += 0.02
        return wish


def test_it_localizes_merges_and_asks_for_a_pallet() -> None:
    source = _source()
    standing = Standing(source)
    wish = source.update(Observation(0.0, 0.0, 0.0, {}, False))
    assert not wish.ready and wish.reason.startswith("no pose from the posts")
    ok, why = source.select_pallet("row_a.r0c1")
    assert not ok and "not merged" in why
    wish = standing.run(2.0)
    assert source.site is not None and source.site.result is not None, source.merge_problem
    assert not wish.ready and wish.reason == "no pallet selected: select one on the tablet"
    # The worker's names; a pallet behind the front row comes from the worker alone.
    assert {"row_a.r0c1", "row_b.r0c1"} <= set(source.names)
    document = source.state_for_tablet()
    behind = next(p for p in document["pallets"] if p["name"] == "row_b.r0c1")
    assert behind["from"] == "worker" and behind["reference_area"]["radius_m"] > 0.4
    assert (
        math.hypot(document["vehicle"]["x_m"] - START.x_m, document["vehicle"]["y_m"] - START.y_m)
        < 0.05
    )
    # The merged worker frame is where the terminal's survey put it (the built-in map's
    # marker is the site's origin): within a few centimetres.
    fitted = source.site.result.worker_in_vehicle
    assert math.hypot(fitted.x_m, fitted.y_m) < 0.06 and abs(fitted.yaw_rad) < math.radians(0.5)


def test_a_selected_pallet_is_planned_beside_the_cycle_and_again_after_a_move() -> None:
    source = _source()
    standing = Standing(source)
    standing.run(2.0)
    ok, why = source.select_pallet("row_z.r9c9")
    assert not ok and why == "no pallet 'row_z.r9c9' in the merged map"
    ok, why = source.select_pallet("row_a.r0c1")
    assert ok, why
    # Asked for in the next cycle, taken in the one after (the job's key listed done).
    wish = source.update(Observation(standing.t_s, 0.0, 0.0, dict(standing.scans), False))
    assert not wish.ready and wish.reason == "planning the way to row_a.r0c1"
    wish = standing.run(0.1)
    assert wish.ready, wish.reason
    assert source.plan is not None and source.state_for_tablet()["path"]
    first = source.plan
    # Driven by hand 0.5 m before anyone engaged: the plan is made again from there.
    standing.run(1.0, START, 0.5)
    moved = standing.pose
    wish = standing.run(0.5, moved)
    assert source.plan is not None and source.plan is not first
    start = source.plan.centres_xy_m()[0]
    assert math.hypot(start[0] - moved.x_m, start[1] - moved.y_m) < 0.05
    assert wish.ready


def test_a_worker_map_that_cannot_be_read_is_a_refusal_that_says_why(tmp_path: Path) -> None:
    broken = tmp_path / "worker.json"
    broken.write_text('{"frame": "worker", "objects": [{"name": 3}]}')
    pallets = _config().pallets.model_copy(update={"worker_map": str(broken)})
    source = _source(_config().model_copy(update={"pallets": pallets}))
    wish = Standing(source).run(1.0)
    assert not wish.ready and wish.reason.startswith(str(broken))
    with pytest.raises(MapFileError, match="cannot read it"):
        load_worker_map(str(tmp_path / "missing.ply"))


def test_the_core_refuses_a_selection_while_engaged_and_tells_the_recorder() -> None:
    core = ControlCore(_config(), None, autopilot=_source())
    told: list[tuple[str, str, bool]] = []
    core.request_listeners.append(lambda kind, name, _t, ok, _m: told.append((kind, name, ok)))
    ok, why = core.select_pallet("row_a.r0c1")
    assert not ok and "not merged" in why
    assert told == [("select_pallet", "row_a.r0c1", False)]
    other = ControlCore(
        _config().model_copy(
            update={
                "engagement": _config().engagement.model_copy(
                    update={"autopilot_source": "hold_straight"}
                )
            }
        ),
        None,
    )
    ok, why = other.select_pallet("row_a.r0c1")
    assert not ok and "not 'pallet'" in why


def test_a_plan_for_an_earlier_selection_is_not_taken_for_a_later_one() -> None:
    source = _source()
    standing = Standing(source)
    standing.run(2.0)
    assert source.select_pallet("row_a.r0c1")[0]
    standing.run(0.02)  # the plan to row_a.r0c1 asked for, not yet taken
    assert source.select_pallet("row_a.r0c2")[0]
    standing.run(0.2)
    assert source.plan is not None and source.target == "row_a.r0c2"
    target = source.plan.target
    assert math.hypot(target.x_m - 4.0, target.y_m - (-1.0)) < 0.1
