"""`dbw calibrate pedals` without the daemon: its samples, its fit into the calibration
file's ``[pedals]`` (and back), what the file refuses, and the vehicle file's sweep.

The samples come from the sweep run faster than real time on the simulated vehicle
(:mod:`appliance.sim.sweep_run`), the same fields the daemon's tap gives.
"""

from __future__ import annotations

from datetime import UTC, datetime
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from appliance.config import load_config
from appliance.config.calibration import Calibration
from appliance.config.calibration_file import read_calibration_file, write_calibration
from appliance.config.calibration_pedals import PedalMapTable, PedalsCalibration
from appliance.config.models import VehicleConfig
from appliance.config.simulated_calibration import simulated_calibration
from appliance.core.core import ControlCore
from appliance.maneuvers.merge import merge_result
from appliance.maneuvers.pedals_step import PedalsStep, map_table
from appliance.maneuvers.steps import StepContext
from appliance.sim.sweep_run import SweepRun, run_sweep

CONFIG = load_config("husky-sim")
WHEN = datetime(2026, 12, 1, 8, 0, tzinfo=UTC)


def simulated_calibration_for(config: VehicleConfig) -> Calibration:
    return Calibration.from_file(simulated_calibration(config.name))


@cache
def sweep() -> SweepRun:
    return run_sweep(CONFIG)


def test_the_fit_merges_into_the_file_and_reads_back_cell_for_cell(tmp_path: Path) -> None:
    step = PedalsStep(StepContext(CONFIG, None))
    report = step.fit(sweep().samples, "pedals.jsonl")
    assert report.accepted and report.result is not None, report.reasons
    path = tmp_path / "cal.toml"
    write_calibration(path, simulated_calibration("husky-sim", created_utc=WHEN))
    said = merge_result(CONFIG, path, report.result)
    assert said.endswith("pedals merged")
    written = read_calibration_file(path, "husky-sim", simulation_enabled=True)
    assert written.pedals is not None and written.items is not None
    assert written.items.pedals is not None and written.items.pedals.raw_data == "pedals.jsonl"
    result = step.accumulator.fit()
    for table, pedal_map in (
        (written.pedals.throttle, result.throttle),
        (written.pedals.brake, result.brake),
    ):
        for (level, band), value in np.ndenumerate(pedal_map.accel_mps2):
            cell = table.cell(level, band)
            assert (cell is None) == (not np.isfinite(value))
            assert cell is None or cell == float(value)


def test_samples_the_sweep_did_not_drive_are_not_taken() -> None:
    step = PedalsStep(StepContext(CONFIG, None))
    base: dict[str, Any] = {
        "t_s": 1.0,
        "speed_mps": 2.0,
        "throttle_actuator_pct": 20.0,
        "brake_actuator_pct": 0.0,
        "sweep_run": 0,
    }
    assert step.take({**base, "mode": "engaged", "sweep_phase": "paused"}) is None
    assert step.take({**base, "mode": "speed_hold", "sweep_phase": "stopping"}) is None
    assert step.accumulator.coverage().throttle_counts.sum() == 0
    assert len(step.accumulator._rows) == 0
    step.take({**base, "mode": "speed_hold", "sweep_phase": "throttle"})
    assert len(step.accumulator._rows) == 1
    problem = step.take({**base, "mode": "speed_hold", "sweep_phase": None})
    assert problem is not None and "not running the pedal sweep" in problem
    assert not step.complete()
    assert step.start_step() == "pedals"  # nothing finished: from the start
    step.take({**base, "mode": "speed_hold", "sweep_phase": "throttle", "sweep_run": 3})
    assert step.start_step() == "pedals@3"  # a resumed run goes on from run 3
    step.take({**base, "speed_mps": 0.0, "mode": "speed_hold", "sweep_phase": "done"})
    assert step.complete()


def table(**change: Any) -> dict[str, Any]:
    values: dict[str, Any] = {
        "pedal_pct": (0.0, 20.0, 40.0),
        "speed_mps": (1.0, 2.0),
        "first_level_by_band": (0, 1),
        "accel_mps2_by_band": ((-0.05, 0.15, 0.36), (0.1, 0.31)),
    }
    return values | change


def test_the_file_refuses_maps_it_cannot_use() -> None:
    PedalMapTable(**table())
    for change in (
        {"first_level_by_band": (0, 2)},  # band 2's levels run past the last
        {"first_level_by_band": (0,)},  # one entry per band
        {"accel_mps2_by_band": ((-0.05, 0.15, 0.36), (0.1, float("nan")))},
        {"accel_mps2_by_band": ((-0.05, 0.15, 0.36), (0.1, 90.0))},
        {"pedal_pct": (0.0, 40.0, 20.0)},
    ):
        with pytest.raises(ValidationError):
            PedalMapTable(**table(**change))
    folded = PedalMapTable(**table(accel_mps2_by_band=((-0.05, 0.4, 0.36), (0.1, 0.31))))
    brake = PedalMapTable(**table(accel_mps2_by_band=((-0.05, -0.5, -1.0), (-0.3, -0.9))))
    with pytest.raises(ValidationError, match="must increase with the pedal"):
        PedalsCalibration(throttle=folded, brake=brake)
    with pytest.raises(ValidationError, match="must decrease with the pedal"):
        PedalsCalibration(throttle=PedalMapTable(**table()), brake=PedalMapTable(**table()))


def test_an_unmeasured_band_is_an_empty_row() -> None:
    empty = PedalMapTable(**table(first_level_by_band=(0, 0), accel_mps2_by_band=((0.1,), ())))
    assert empty.cell(0, 1) is None and empty.cell(0, 0) == 0.1


def husky_with(**sections: dict[str, Any]) -> VehicleConfig:
    data = CONFIG.model_dump()
    for section, values in sections.items():
        data[section] = data[section] | values
    return VehicleConfig.model_validate(data)


@pytest.mark.parametrize(
    ("sections", "message"),
    [
        ({"pedal_sweep": {"throttle_levels_pct": (20.0, 50.0)}}, "past limits.throttle_max_pct"),
        ({"pedal_sweep": {"speed_band_edges_mps": (0.5, 4.5)}}, "must end below top_speed"),
        ({"pedal_sweep": {"brake_levels_pct": (10.0, 5.0)}}, "must be increasing"),
        ({"pedal_sweep": {"top_speed_mps": 5.0}}, "must not exceed limits.max_speed_mps"),
        ({"pedal_sweep": {"throttle_levels_pct": (0.0, 20.0)}}, r"must lie in \(0, 100\]"),
        (
            {
                "engagement": {
                    "hold_to_move": True,
                    "hold_to_move_stop_distance_m": 5.0,
                    "max_set_speed_mps": 3.0,
                },
                "pedal_sweep": {"top_speed_mps": 4.0},
            },
            "under hold-to-move",
        ),
    ],
)
def test_the_vehicle_file_refuses_a_sweep_the_limits_would_clamp(
    sections: dict[str, dict[str, Any]], message: str
) -> None:
    with pytest.raises(ValidationError, match=message):
        husky_with(**sections)


def test_the_default_sweep_past_a_vehicles_limits_loads_but_is_not_armed() -> None:
    config = husky_with(limits={"throttle_max_pct": 30.0})
    core = ControlCore(config, simulated_calibration_for(config))
    accepted, message = core.maneuver_request("start", "pedals", 0.0)
    assert not accepted and "past limits.throttle_max_pct (30.0)" in message


def test_a_vehicle_whose_pc104_closes_the_speed_loop_is_not_held_to_the_sweep() -> None:
    flatbed = load_config("flatbed-sim")
    assert flatbed.speed_path == "pc104"
    assert flatbed.pedal_sweep.top_speed_mps > flatbed.limits.max_speed_mps


def test_map_table_keeps_each_bands_contiguous_levels() -> None:
    step = PedalsStep(StepContext(CONFIG, None))
    assert step.fit(sweep().samples, None).accepted
    brake = map_table(step.accumulator.fit().brake)
    # The hardest brake fills only the lowest band (it crosses the others unsettled).
    assert len(brake.accel_mps2_by_band[0]) > len(brake.accel_mps2_by_band[-1])
    assert all(first == 0 for first in brake.first_level_by_band)
