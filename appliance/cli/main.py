"""The `dbw` group: logging options, `dbw run` (what the systemd unit starts), and every
command group of this package registered under it."""

from __future__ import annotations

import sys

import click

from appliance import __version__
from appliance.cli.calibrate import calibrate
from appliance.cli.calibrate_maneuvers import add_maneuver_commands
from appliance.cli.calibration import calibration
from appliance.cli.common import CONFIG_OPTION, load_or_exit
from appliance.cli.config import config
from appliance.cli.control import CONTROL_COMMANDS
from appliance.cli.features import features
from appliance.cli.gnss import gnss
from appliance.cli.lms111 import lms111
from appliance.cli.localize import localize
from appliance.cli.merge import merge
from appliance.cli.record import record, replay
from appliance.cli.route import route
from appliance.cli.route_record import route_record as _route_record  # noqa: F401 (registers)
from appliance.cli.sim import sim
from appliance.logs import LEVELS, configure_logging


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="dbw")
@click.option(
    "--log-level",
    type=click.Choice(LEVELS),
    default="info",
    show_default=True,
    help="Lowest level of log events to print.",
)
@click.option(
    "--log-format",
    type=click.Choice(["auto", "json", "console"]),
    default="auto",
    show_default=True,
    help="auto: JSON lines when stdout is not a terminal (journald), readable text on one.",
)
def cli(log_level: str, log_format: str) -> None:
    """dbw-applique: drive-by-wire appliqué runtime for retrofitted heavy vehicles."""
    configure_logging(log_level, json=None if log_format == "auto" else log_format == "json")


@cli.command()
@CONFIG_OPTION
@click.option(
    "--duration-s",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Stop cleanly after this many seconds (demos and tests). Default: run until signalled.",
)
@click.option(
    "--record/--no-record",
    default=None,
    help="Record to MCAP (recording.directory) or not. Default: the vehicle file's "
    "recording.enabled (on for a vehicle, off for the built-in simulated ones).",
)
def run(config_name: str | None, duration_s: float | None, record: bool | None) -> None:
    """Run the daemon (what the systemd unit starts)."""
    from appliance.daemon import run_daemon

    vehicle = load_or_exit(config_name)
    sys.exit(run_daemon(vehicle, duration_s=duration_s, record=record))


cli.add_command(config)
cli.add_command(record)
cli.add_command(replay)
cli.add_command(lms111)
cli.add_command(sim)
cli.add_command(calibration)
add_maneuver_commands(calibrate)
cli.add_command(calibrate)
cli.add_command(features)
cli.add_command(localize)
cli.add_command(merge)
cli.add_command(gnss)
cli.add_command(route)
for _command in CONTROL_COMMANDS:
    cli.add_command(_command)


def main() -> None:
    cli()
