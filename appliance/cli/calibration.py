"""`dbw calibration ...`: check, show and write the calibration file the daemon needs.

`check` answers "will self-check accept this file on this vehicle?" before the vehicle is
started, with the same loader the daemon uses; `show` prints what the daemon would use
(the built-in simulated calibration included); `write-simulated` writes the simulated
vehicle's calibration to a file, for a daemon in another process that talks to `dbw sim`.
"""

from __future__ import annotations

import json
import math
import sys

import click

from appliance.cli.common import CONFIG_OPTION, EXIT_CONFIG_ERROR, load_or_exit
from appliance.config import VehicleConfig
from appliance.config.calibration import Calibration, CalibrationFile
from appliance.config.calibration_file import (
    CalibrationError,
    dumps_calibration,
    read_vehicle_calibration,
    write_calibration,
)
from appliance.config.simulated_calibration import servo_of, simulated_calibration
from appliance.sim.scanner_truth import with_simulated_scanners


def _read_or_exit(file: str, config: VehicleConfig) -> CalibrationFile:
    try:
        return read_vehicle_calibration(config, file)
    except CalibrationError as exc:
        click.echo(exc.render(), err=True)
        sys.exit(EXIT_CONFIG_ERROR)


def _summary(calibration: Calibration) -> str:
    low_rad, high_rad = calibration.valid_tyre_range_rad
    return (
        f"vehicle {calibration.vehicle_name!r}, "
        f"pot centre {calibration.pot_centre_counts:.1f} counts, "
        f"tyre range {math.degrees(low_rad):.1f}..{math.degrees(high_rad):.1f} deg"
    )


@click.group()
def calibration() -> None:
    """Check, show and write steering calibration files."""


@calibration.command("check")
@click.argument("file")
@CONFIG_OPTION
def calibration_check(file: str, config_name: str | None) -> None:
    """Validate FILE for the vehicle; print every problem and exit 2 if there is any."""
    config = load_or_exit(config_name)
    loaded = Calibration.from_file(_read_or_exit(file, config))
    click.echo(f"{file}: OK ({_summary(loaded)})")


@calibration.command("show")
@click.argument("file", required=False)
@CONFIG_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of TOML.")
def calibration_show(file: str | None, config_name: str | None, as_json: bool) -> None:
    """Print the calibration in FILE (default: the config's paths.calibration_file)."""
    config = load_or_exit(config_name)
    file = file if file is not None else config.paths.calibration_file
    model = _read_or_exit(file, config)
    loaded = Calibration.from_file(model)
    if as_json:
        low_rad, high_rad = loaded.valid_tyre_range_rad
        data = {
            "file": file,
            "calibration": model.model_dump(mode="json"),
            "valid_wheel_range_rad": list(loaded.valid_wheel_range_rad),
            "valid_tyre_range_deg": [math.degrees(low_rad), math.degrees(high_rad)],
        }
        click.echo(json.dumps(data, indent=2))
        return
    click.echo(f"# {file}: {_summary(loaded)}")
    click.echo(dumps_calibration(model), nl=False)


@calibration.command("write-simulated")
@click.argument("out")
@CONFIG_OPTION
def calibration_write_simulated(out: str, config_name: str | None) -> None:
    """Write the simulated vehicle's calibration, for the config's vehicle name, to OUT."""
    config = load_or_exit(config_name)
    if not config.simulation.enabled:
        # Legitimate for a daemon talking to `dbw sim` (its config disables simulation),
        # but on a real vehicle this file would pass self-check with a made-up mapping.
        click.echo(
            f"warning: vehicle {config.name!r} has simulation.enabled = false; this file is "
            "the simulated vehicle's mapping: use it only with `dbw sim`, never on a vehicle",
            err=True,
        )
    servo = servo_of(config.simulation.steering.steering_ratio)
    model = with_simulated_scanners(simulated_calibration(config.name, servo=servo), config)
    try:
        write_calibration(out, model)
    except OSError as exc:
        click.echo(f"{out}: cannot write the calibration: {exc}", err=True)
        sys.exit(EXIT_CONFIG_ERROR)
    click.echo(f"wrote {out} ({_summary(Calibration.from_file(model))})")
