"""The simulated vehicle's scanners: drawn errors from the vehicle file, true mounts exposed."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
from pydantic import ValidationError

from appliance.config import VehicleConfig, load_config
from appliance.config.models import Simulation
from appliance.sim import draw_scanner_errors, ideal_scanner, load_site, render_scan
from appliance.simulator import Simulator, build_simulator
from drivers.lms111.mounted import mount_pose
from safety.watchdog import RestartPolicy


def _config(**simulation: object) -> VehicleConfig:
    base = load_config("sim")
    return base.model_copy(update={"simulation": base.simulation.model_copy(update=simulation)})


@pytest.fixture
def simulators() -> Iterator[list[Simulator]]:
    built: list[Simulator] = []
    yield built
    for simulator in built:
        simulator.close()


def test_the_vehicle_file_chooses_the_scanner_model_and_its_seed() -> None:
    default = Simulation()
    assert (default.scanner_model, default.scanner_seed) == ("realistic", 1)
    assert Simulation(scanner_model="ideal", scanner_seed=42).scanner_seed == 42
    for bad in ({"scanner_model": "perfect"}, {"scanner_seed": -1}, {"scanner_seed": 2**32}):
        with pytest.raises(ValidationError):
            Simulation.model_validate(bad)
    with pytest.raises(ValidationError, match="scanner_range_bias_m"):
        Simulation.model_validate({"scanner_range_bias_m": 0.01})  # replaced by the model


def test_each_twin_scans_from_its_true_mount_with_its_drawn_errors(
    simulators: list[Simulator],
) -> None:
    config = _config(scanner_seed=9)
    simulator = build_simulator(config, RestartPolicy())
    simulators.append(simulator)
    mounts = {
        "left": config.geometry.scanner_left_mount,
        "right": config.geometry.scanner_right_mount,
    }
    offsets = []
    for index, side in enumerate(("left", "right")):
        twin = simulator.scanner_twins[side]
        errors = draw_scanner_errors(9, index, realistic=True)
        assert twin.errors == errors
        assert twin.mount == mount_pose(mounts[side])  # what the daemon is told
        assert twin.true_mount == errors.true_mount(twin.mount)
        dx_m, dy_m = twin.true_mount.x_m - twin.mount.x_m, twin.true_mount.y_m - twin.mount.y_m
        assert 0.0 < math.hypot(dx_m, dy_m) <= 0.005 * math.sqrt(2.0)
        assert 0.0 < abs(twin.true_mount.yaw_rad - twin.mount.yaw_rad) <= math.radians(0.3)
        offsets.append(twin.errors.range_offset_m)
    assert offsets[0] != offsets[1]
    # Same file, same vehicle: the draw is reproducible.
    again = build_simulator(config, RestartPolicy())
    simulators.append(again)
    assert again.scanner_twins["left"].errors == simulator.scanner_twins["left"].errors


def test_an_ideal_simulation_has_ideal_scanners_on_their_configured_mounts(
    simulators: list[Simulator],
) -> None:
    config = _config(scanner_model="ideal")
    simulator = build_simulator(config, RestartPolicy())
    simulators.append(simulator)
    site = load_site(config.simulation.site)
    for twin in simulator.scanner_twins.values():
        assert twin.errors == ideal_scanner()
        assert twin.true_mount == twin.mount
        scan = twin.device.measure(1.0)  # what the next telegram carries
        assert scan is not None
        vehicle = twin.pose_source(1.0)
        exact, _ = render_scan(
            site,
            1.0,
            vehicle,
            twin.mount,
            rng=np.random.default_rng(0),
            errors=ideal_scanner(),
            step_rad=scan.angular_step_rad,
        )
        assert np.count_nonzero(exact) > 100
        np.testing.assert_allclose(scan.ranges_m, exact, atol=0.0006)  # whole millimetres
