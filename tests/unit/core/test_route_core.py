"""The `route` source through the whole control core on the pedals path, with fake time:
engaged on a route the core steers it, and a fix that stops coming hands the steering
back within one control cycle of the fix-age limit, saying why.

The bench vehicle drives a straight route east at 2 m/s; its GNSS/INS epochs are made by
hand at 10 Hz from where it is, each seen 50 ms after its measurement, as the daemon's
receiver task delivers them.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from appliance.config.models import VehicleConfig
from appliance.core.core import ControlCore
from appliance.core.inputs import ControlInputs
from appliance.core.output import CoreOutput
from appliance.localization.local_frame import LocalFrame
from appliance.modes import AUTOMATIC_MODES, Mode
from appliance.routes import Route, RouteStore
from drivers.actuators.messages import Buttons
from tests.unit.core.test_pedals_path import GNSS_LATENCY_S, PedalBench, gnss_epoch, pedals_config
from tests.unit.core.vehicle import SIM_CALIBRATION

ORIGIN = {"lat_deg": 42.4591, "lon_deg": -71.2674, "alt_m": 100.0}
DT_S = 0.02
EPOCH_PERIOD_S = 0.1


def route_config(routes: Path) -> VehicleConfig:
    data = pedals_config().model_dump(mode="json")
    data["engagement"] = data.get("engagement", {}) | {"autopilot_source": "route"}
    data["devices"]["gnss"] = {"port": "/dev/null", "receiver_latency_s": GNSS_LATENCY_S}
    data["positioning"] = {"origin": ORIGIN}
    data["route"] = {"routes_dir": str(routes), "selected": "yard"}
    return VehicleConfig.model_validate(data)


class RouteBench(PedalBench):
    """The pedal bench with a position: it starts ``offset_m`` left of a route along the
    east axis and moves east at its speed; epochs every 0.1 s until ``lost_at_s``."""

    def __init__(self, offset_m: float) -> None:
        super().__init__()
        self.north_m = offset_m
        self.lost_at_s = math.inf
        self.last_epoch = None
        self.epoch_seq = 0

    def inputs(self, age_limits_s: dict[str, float] | None = None) -> ControlInputs:
        base = super().inputs(age_limits_s)
        measured_s = self.now_s - GNSS_LATENCY_S
        due = math.floor(measured_s / EPOCH_PERIOD_S + 1e-9) * EPOCH_PERIOD_S
        if measured_s < self.lost_at_s and (
            self.last_epoch is None or due > self.last_epoch.measurement_time_s + 1e-9
        ):
            epoch = gnss_epoch(due, max(self.speed_mps, 0.0))
            self.last_epoch = dataclasses.replace(
                epoch, east_m=20.0 + self.distance_m, north_m=self.north_m
            )
            self.epoch_seq += 1
        # Once lost, the daemon's input keeps the last epoch it had, aging.
        return dataclasses.replace(base, gnss=self.last_epoch, gnss_seq=self.epoch_seq)


def engaged_on_route(tmp_path: Path) -> tuple[ControlCore, RouteBench]:
    frame = LocalFrame(ORIGIN["lat_deg"], ORIGIN["lon_deg"], ORIGIN["alt_m"])
    line = np.column_stack((np.linspace(0.0, 400.0, 801), np.zeros(801)))
    RouteStore(tmp_path).save(Route.from_enu("yard", line, frame))
    core = ControlCore(route_config(tmp_path), SIM_CALIBRATION)
    vehicle = RouteBench(offset_m=0.3)
    vehicle.run(core, 1.0, DT_S)
    assert not core.engage_blockers(), core.engage_blockers()
    vehicle.press(Buttons.ENGAGE)
    vehicle.throttle_pedal(30.0)
    out = vehicle.step(core, DT_S)
    assert out.mode is Mode.ENGAGED, core.engage_blockers()
    while vehicle.speed_mps < 2.0:
        assert vehicle.step(core, DT_S).mode is Mode.ENGAGED
    return core, vehicle


def steering_automatic(out: CoreOutput) -> bool:
    return out.mode in AUTOMATIC_MODES and out.steer_tyre_rad is not None


def test_engaged_on_a_route_the_core_steers_it_back_onto_the_line(tmp_path: Path) -> None:
    core, vehicle = engaged_on_route(tmp_path)
    outs = vehicle.run(core, 6.0, DT_S)
    assert all(steering_automatic(out) for out in outs)
    follow = core.status(vehicle.now_s)["autopilot"]["follow"]
    assert abs(follow["cross_track_m"]) < 0.3  # from 0.3 m left, closing
    assert vehicle.north_m == pytest.approx(0.3)  # the bench does not move sideways


@pytest.mark.parametrize("lost_after_s", [0.0, 0.03, 0.07])
def test_a_lost_fix_hands_steering_back_within_one_cycle_of_its_age_limit(
    tmp_path: Path, lost_after_s: float
) -> None:
    core, vehicle = engaged_on_route(tmp_path)
    max_age_s = core.config.positioning.max_fix_age_s
    vehicle.lost_at_s = vehicle.now_s - GNSS_LATENCY_S + lost_after_s
    last_automatic_s = None
    while True:
        out = vehicle.step(core, DT_S)
        assert vehicle.last_epoch is not None
        age_s = vehicle.now_s - vehicle.last_epoch.measurement_time_s
        if not steering_automatic(out):
            break
        last_automatic_s = vehicle.now_s
        assert age_s <= max_age_s + 1e-9, "steered on a fix older than its limit"
    assert last_automatic_s is not None
    # Handed back in the first cycle past the limit, not later.
    assert max_age_s < age_s <= max_age_s + DT_S + 1e-9, age_s
    assert out.mode not in AUTOMATIC_MODES
    assert not out.throttle.enable or out.throttle.position_pct == 0.0
    status = core.status(vehicle.now_s)
    said = f"{status.get('faults')} {status.get('fault_history')} {status.get('last_refusal')}"
    assert "fix lost" in said, said
