"""`dbw`: the one command a person uses on the vehicle and on the bench.

Errors a person can fix (a bad config file) are printed as plain sentences with exit
status 2; tracebacks are for bugs only.
"""

from __future__ import annotations

import json
import sys

import click

from appliance import __version__
from appliance.cli_lms111 import lms111
from appliance.config import BUILTIN_PROFILES, ConfigError, VehicleConfig, load_config
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
    click.echo(_to_toml(data))


def _to_toml(data: dict[str, object], prefix: str = "") -> str:
    """Render the effective config in TOML so it can be copied into a vehicle file."""
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict)}
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    lines = []
    if prefix and scalars:
        lines.append(f"[{prefix}]")
    for key, value in scalars.items():
        lines.append(f"{key} = {json.dumps(value)}")
    out = "\n".join(lines)
    for key, value in tables.items():
        assert isinstance(value, dict)
        sub = _to_toml(value, f"{prefix}.{key}" if prefix else key)
        out = f"{out}\n\n{sub}" if out else sub
    return out


cli.add_command(lms111)


def main() -> None:
    cli()
