"""`dbw run`: the daemon, what the systemd unit starts."""

from __future__ import annotations

import sys

import click

from appliance.cli.common import CONFIG_OPTION, load_or_exit


@click.command()
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
