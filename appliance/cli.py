"""`dbw`: the one command a person uses on the vehicle and on the bench.

Errors a person can fix (a bad config file) are printed as plain sentences with exit
status 2; tracebacks are for bugs only.
"""

from __future__ import annotations

import json
import sys

import click

from appliance import __version__
from appliance.cli_calibration import calibration
from appliance.cli_control import CONTROL_COMMANDS
from appliance.cli_lms111 import lms111
from appliance.cli_sim import sim
from appliance.config import BUILTIN_PROFILES, ConfigError, VehicleConfig, load_config
from appliance.config.loader import to_toml
from appliance.logs import LEVELS, configure_logging

EXIT_CONFIG_ERROR = 2

CONFIG_HELP = (
    "A TOML file, or the name of a built-in profile ("
    + ", ".join(BUILTIN_PROFILES)
    + "). Default: sim, the built-in simulated vehicle."
)


def _load_or_exit(name_or_path: str | None) -> VehicleConfig:
    try:
        return load_config(name_or_path)
    except ConfigError as exc:
        click.echo(exc.render(), err=True)
        sys.exit(EXIT_CONFIG_ERROR)


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
@click.option("--config", "config_name", metavar="FILE|PROFILE", help=CONFIG_HELP)
@click.option(
    "--duration-s",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Stop cleanly after this many seconds (demos and tests). Default: run until signalled.",
)
def run(config_name: str | None, duration_s: float | None) -> None:
    """Run the daemon (what the systemd unit starts)."""
    from appliance.daemon import run_daemon

    config = _load_or_exit(config_name)
    sys.exit(run_daemon(config, duration_s=duration_s))


@cli.group()
def config() -> None:
    """Check and show vehicle configuration files."""


@config.command("check")
@click.argument("file")
def config_check(file: str) -> None:
    """Validate FILE; print every problem and exit 2 if there is any."""
    loaded = _load_or_exit(file)
    click.echo(f"{file}: OK (vehicle {loaded.name!r}, kind {loaded.kind})")


@config.command("show")
@click.argument("file", required=False)
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of TOML-like text.")
def config_show(file: str | None, as_json: bool) -> None:
    """Print the effective configuration of FILE (default: sim), defaults included."""
    loaded = _load_or_exit(file)
    data = loaded.model_dump(mode="json")
    if as_json:
        click.echo(json.dumps(data, indent=2))
        return
    click.echo(to_toml(data))


cli.add_command(lms111)
cli.add_command(sim)
cli.add_command(calibration)
for _command in CONTROL_COMMANDS:
    cli.add_command(_command)


def main() -> None:
    cli()
