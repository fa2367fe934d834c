"""`dbw` imports a command group only when it runs one (appliance/cli/lazy.py).

Checked in fresh interpreters: what a module imports depends on what was imported
before it, and this test process has imported everything.
"""

from __future__ import annotations

import json
import subprocess
import sys

import click
import pytest
from click.testing import CliRunner

from appliance.cli.control import CONTROL_COMMANDS
from appliance.cli.lazy import LazyGroup
from appliance.cli.main import COMMANDS, SUMMARIES, cli

# What only some commands need: the control core (replay, the calibration fits from a
# recording), the pallet planner and scipy (which brings most of the rest).
HEAVY = ("appliance.core.core", "appliance.recording.replay", "appliance.guidance.pallet_plan")


def _imported_by(*modules: str, then: str = "") -> set[str]:
    """The modules a fresh interpreter has after importing ``modules`` (and running
    ``then``)."""
    code = (
        "import contextlib, importlib, io, json, sys\n"
        f"for name in {list(modules)!r}: importlib.import_module(name)\n"
        f"{then}\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    return set(json.loads(done.stdout))


@pytest.mark.parametrize(
    ("modules", "scipy"),
    [
        (("appliance.cli.main",), False),
        (("appliance.cli.main", "appliance.cli.control"), False),  # dbw status, engage, ...
        # The simulated vehicle: its scanners' cast is compiled by numba, whose import
        # checks scipy's version (numba/__init__.py, _ensure_critical_deps).
        (("appliance.cli.main", "appliance.cli.sim"), True),
        (("appliance.cli.main", "appliance.cli.calibrate"), True),  # its fits use scipy
    ],
)
def test_a_command_does_not_import_what_only_others_need(
    modules: tuple[str, ...], scipy: bool
) -> None:
    imported = _imported_by(*modules)
    assert not imported & set(HEAVY), sorted(imported & set(HEAVY))
    assert scipy or "scipy" not in imported


def test_dbw_help_lists_every_command_without_importing_one() -> None:
    help_only = (
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
        "    sys.modules['appliance.cli.main'].cli(['--help'])"
    )
    imported = _imported_by("appliance.cli.main", then=help_only)
    commands = {target.partition(":")[0] for target in COMMANDS.values()}
    assert not imported & commands, sorted(imported & commands)
    assert "appliance.config.models" not in imported  # nor the vehicle file's models


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_each_summary_is_what_the_command_itself_says(name: str) -> None:
    command = cli.get_command(click.Context(cli), name)
    assert command is not None
    summary = click.Command(name, help=SUMMARIES[name])
    for limit in range(10, 200):  # as wide as any terminal lists it
        assert summary.get_short_help_str(limit) == command.get_short_help_str(limit)


def test_every_command_is_listed_loads_and_says_what_it_does() -> None:
    result = CliRunner().invoke(cli, ["--help"])
    assert result.exit_code == 0, result.output
    context = click.Context(cli)
    assert SUMMARIES.keys() == COMMANDS.keys()
    for name in COMMANDS:
        command = cli.get_command(context, name)
        assert command is not None and command.name == name
        assert f"  {name} " in result.output  # listed, with its summary
    assert "run" in cli.list_commands(context)
    for command in CONTROL_COMMANDS:  # the daemon's commands, each under the top level
        assert cli.get_command(context, str(command.name)) is command


def test_a_group_s_lazy_subcommands_run() -> None:
    result = CliRunner().invoke(cli, ["route", "--help"])
    assert result.exit_code == 0 and "record" in result.output
    result = CliRunner().invoke(cli, ["calibrate", "--help"])
    assert result.exit_code == 0 and "pot-map" in result.output and "scanners" in result.output
    result = CliRunner().invoke(cli, ["sim", "dock", "--help"])
    assert result.exit_code == 0 and "--start-x-m" in result.output


def test_a_misnamed_command_is_a_clear_error() -> None:
    group = LazyGroup("g", lazy_subcommands={"x": "appliance.cli.lazy:LazyGroup"})
    with pytest.raises(TypeError, match="not a click command"):
        group.get_command(click.Context(group), "x")
    assert group.get_command(click.Context(group), "nothing") is None
