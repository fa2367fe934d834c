"""The `dbw` group: logging options, and every command of this package (`dbw run`, what
the systemd unit starts, among them) registered under it."""

from __future__ import annotations

import click

from appliance import __version__
from appliance.cli.lazy import LazyGroup
from appliance.logs import LEVELS, configure_logging

# Every command group, imported when it is run (see appliance/cli/lazy.py), and
# what `dbw --help` lists it with, so that listing them imports none (each is the
# command's own first sentence: tests/unit/test_cli_lazy.py holds them to it).
COMMANDS = {
    "calibrate": "appliance.cli.calibrate:calibrate",
    "calibration": "appliance.cli.calibration:calibration",
    "config": "appliance.cli.config:config",
    "disengage": "appliance.cli.control:disengage",
    "engage": "appliance.cli.control:engage",
    "estop": "appliance.cli.control:estop",
    "estop-reset": "appliance.cli.control:estop_reset",
    "features": "appliance.cli.features:features",
    "gnss": "appliance.cli.gnss:gnss",
    "hold": "appliance.cli.control:hold",
    "lms111": "appliance.cli.lms111:lms111",
    "localize": "appliance.cli.localize:localize",
    "merge": "appliance.cli.merge:merge",
    "record": "appliance.cli.record:record",
    "replay": "appliance.cli.record:replay",
    "route": "appliance.cli.route:route",
    "run": "appliance.cli.run:run",
    "sim": "appliance.cli.sim:sim",
    "speed-down": "appliance.cli.control:speed_down",
    "speed-up": "appliance.cli.control:speed_up",
    "status": "appliance.cli.control:status",
}
SUMMARIES = {
    "calibrate": "Measure calibrations on the vehicle: the steering maneuvers, the scanners.",
    "calibration": "Check, show and write steering calibration files.",
    "config": "Check and show vehicle configuration files.",
    "disengage": "Hand everything back to the operator (the manual-override button); in "
    "ERROR with the faults cleared, return to READY.",
    "engage": "Engage automatic steering, as the panel's engage button does (READY to ENGAGED).",
    "estop": "Emergency stop: brake fully and latch ESTOP until estop-reset.",
    "estop-reset": "Complete the e-stop reset: leave ESTOP for READY at best (never engaged).",
    "features": "The segments, lines and cylinders in each scan of an LMS111 recording.",
    "gnss": "Probe and record a GNSS/INS receiver (NMEA 0183 on a serial port).",
    "hold": "Press the hold-to-move button for SECONDS, printing progress, then release it.",
    "lms111": "Probe, record and decode a SICK LMS111.",
    "localize": "Replay two scanners' recordings through the launcher localizer; print the track.",
    "merge": "Merge WORKER_MAP into VEHICLE_MAP through their pallets (JSON object lists or PLY).",
    "record": "Recordings the daemon writes (MCAP; README, Recording and replay).",
    "replay": "Run the recorded inputs of FILE through the core again and compare the outputs.",
    "route": "List, show, check and import the routes the autopilot follows (GeoJSON).",
    "run": "Run the daemon (what the systemd unit starts).",
    "sim": "Run the simulated vehicle and print its endpoints (and a config for `dbw run`).",
    "speed-down": "The - button: lower the set speed one step.",
    "speed-up": "The + button: raise the set speed one step (from ENGAGED, start speed hold).",
    "status": "Show the daemon's mode, faults, inputs, commands and services.",
}


@click.group(
    cls=LazyGroup,
    lazy_subcommands=COMMANDS,
    summaries=SUMMARIES,
    context_settings={"help_option_names": ["-h", "--help"]},
)
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


def main() -> None:
    cli()
