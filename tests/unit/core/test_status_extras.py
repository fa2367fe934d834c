"""What the status document carries for the operator page beyond the core's view.

The dock source gives the launcher's geometry as its localizer knows it (the page draws
Qian et al.'s Fig. 8 from it instead of a built-in site); a source without one adds none.
"""

from __future__ import annotations

from appliance.config import load_config
from appliance.config.calibration_file import BUILTIN_SIMULATED, load_calibration
from appliance.core.core import ControlCore
from appliance.localization.launcher_map import LauncherMap


def test_the_dock_source_shows_the_launcher_it_localizes_against() -> None:
    config = load_config("flatbed-sim")
    calibration = load_calibration(BUILTIN_SIMULATED, config.name, simulation_enabled=True)
    core = ControlCore(config, calibration)
    launcher = core.status(0.0)["autopilot"]["launcher"]
    known = LauncherMap()
    assert launcher["front_board_width_m"] == known.front_board_width_m
    assert launcher["side_board_sweep_deg"] == known.side_board_sweep_deg
    assert [(c["x_m"], c["y_m"]) for c in launcher["cylinders"]] == [
        (c.x_m, c.y_m) for c in known.cylinders
    ]


def test_a_source_without_a_launcher_or_a_route_adds_neither() -> None:
    config = load_config("sim")
    calibration = load_calibration(BUILTIN_SIMULATED, config.name, simulation_enabled=True)
    pilot = ControlCore(config, calibration).status(0.0)["autopilot"]
    assert "launcher" not in pilot and "route_window" not in pilot
