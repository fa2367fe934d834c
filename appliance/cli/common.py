"""What every command group shares: how a vehicle is named, and how a bad one (or any bad
input) ends the command."""

from __future__ import annotations

import sys
from typing import Any, NoReturn

import click

from appliance.config import BUILTIN_PROFILES, ConfigError, VehicleConfig, load_config

# A problem the person can fix (a bad vehicle or calibration file): one line each, no traceback.
EXIT_CONFIG_ERROR = 2

CONFIG_HELP = (
    "A TOML file, or the name of a built-in profile ("
    + ", ".join(BUILTIN_PROFILES)
    + "). Default: sim, the built-in simulated vehicle."
)

CONFIG_OPTION = click.option("--config", "config_name", metavar="FILE|PROFILE", help=CONFIG_HELP)


def load_or_exit(name_or_path: str | None) -> VehicleConfig:
    """The vehicle file, or every problem with it printed and exit status 2."""
    try:
        return load_config(name_or_path)
    except ConfigError as exc:
        click.echo(exc.render(), err=True)
        sys.exit(EXIT_CONFIG_ERROR)


def bad_input(message: str) -> NoReturn:
    """One line on stderr, exit status 2: input the person can fix, so no traceback."""
    click.echo(f"error: {message}", err=True)
    sys.exit(EXIT_CONFIG_ERROR)


def draw_png(path: str, draw: Any) -> str | None:
    """``draw(plt) -> figure``, saved as a PNG; None when drawn, else why not (a picture
    is never worth exit 2)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "not drawn: matplotlib is not installed"
    try:
        figure = draw(plt)
        figure.savefig(path, dpi=120)
        plt.close(figure)
    except (OSError, ValueError) as exc:
        return f"not drawn: {exc}"
    return None
