"""`dbw config ...`: check and show vehicle files, with the loader the daemon uses."""

from __future__ import annotations

import json

import click

from appliance.cli.common import load_or_exit
from appliance.config.loader import to_toml


@click.group()
def config() -> None:
    """Check and show vehicle configuration files."""


@config.command("check")
@click.argument("file")
def config_check(file: str) -> None:
    """Validate FILE; print every problem and exit 2 if there is any."""
    loaded = load_or_exit(file)
    click.echo(f"{file}: OK (vehicle {loaded.name!r}, kind {loaded.kind})")


@config.command("show")
@click.argument("file", required=False)
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of TOML-like text.")
def config_show(file: str | None, as_json: bool) -> None:
    """Print the effective configuration of FILE (default: sim), defaults included."""
    loaded = load_or_exit(file)
    data = loaded.model_dump(mode="json")
    if as_json:
        click.echo(json.dumps(data, indent=2))
        return
    click.echo(to_toml(data))
