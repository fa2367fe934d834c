"""`dbw status`, `dbw engage`, `dbw hold`, ...: the daemon's state and bench commands.

They talk to the running daemon over its local control socket (see
:mod:`appliance.control_socket`). Exit status: 0 the daemon accepted, 1 it refused (its
reasons are printed), 2 there is no talking to it (no daemon, no permission, bad config).
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NoReturn

import click

from appliance.cli.status_view import as_dict, as_strings, clean_text, render_status, speed_line
from appliance.config import BUILTIN_PROFILES, ConfigError, load_config
from appliance.control_client import ControlClient, query_sync
from appliance.control_protocol import ControlSocketError

EXIT_ACCEPTED = 0
EXIT_REFUSED = 1
EXIT_NO_DAEMON = 2
HOLD_REPORT_PERIOD_S = 0.5

_CONFIG_HELP = (
    "Take the socket path (paths.control_socket) from this TOML file or built-in profile ("
    + ", ".join(BUILTIN_PROFILES)
    + "). Default: sim."
)


def _socket_options(command: Callable[..., None]) -> Callable[..., None]:
    command = click.option(
        "--socket",
        "socket_path",
        metavar="PATH",
        default=None,
        help="The daemon's control socket. Default: paths.control_socket of --config "
        f"(else $DBW_CONFIG, else {INSTALLED_CONFIG} if it exists, else the sim profile).",
    )(command)
    return click.option("--config", "config_name", metavar="FILE|PROFILE", help=_CONFIG_HELP)(
        command
    )


# Where the systemd unit's vehicle file lives (README, "Running on the vehicle"): on the
# vehicle PC, `dbw status` with no options talks to the daemon systemd runs.
INSTALLED_CONFIG = "/etc/dbw/vehicle.toml"


def running_config_name(config_name: str | None) -> str | None:
    """The vehicle file of the daemon a control command talks to: ``--config``, else
    ``DBW_CONFIG``, else the installed one, else None (the built-in default)."""
    if config_name is not None:
        return config_name
    return os.environ.get("DBW_CONFIG") or (
        INSTALLED_CONFIG if os.path.exists(INSTALLED_CONFIG) else None
    )


def _socket_path(socket_path: str | None, config_name: str | None) -> str:
    if socket_path:
        return socket_path
    try:
        return load_config(running_config_name(config_name)).paths.control_socket
    except ConfigError as exc:
        click.echo(exc.render(), err=True)
        sys.exit(EXIT_NO_DAEMON)


def _fail(exc: ControlSocketError) -> NoReturn:
    click.echo(f"dbw: {exc}", err=True)
    sys.exit(EXIT_NO_DAEMON)


@click.command("status")
@click.option("--json", "as_json", is_flag=True, help="Print the status document as JSON.")
@click.option(
    "--watch",
    "watch_s",
    metavar="SECONDS",
    type=click.FloatRange(min=0.1),
    default=None,
    help="Print it again every SECONDS until Ctrl-C (keeps trying if the daemon goes away).",
)
@click.option(
    "--count",
    type=click.IntRange(min=1),
    default=None,
    help="With --watch: stop after this many updates.",
)
@_socket_options
def status(
    as_json: bool,
    watch_s: float | None,
    count: int | None,
    socket_path: str | None,
    config_name: str | None,
) -> None:
    """Show the daemon's mode, faults, inputs, commands and services."""
    path = _socket_path(socket_path, config_name)
    clear = watch_s is not None and not as_json and sys.stdout.isatty()
    shown = 0
    try:
        while True:
            try:
                click.echo(_status_text(path, as_json))
            except ControlSocketError as exc:
                if watch_s is None:
                    _fail(exc)
                click.echo(f"dbw: {exc}", err=True)
            shown += 1
            if watch_s is None or (count is not None and shown >= count):
                return
            time.sleep(watch_s)
            if clear:
                click.clear()
    except KeyboardInterrupt:
        return


def _status_text(path: str, as_json: bool) -> str:
    reply = query_sync(path, {"op": "status"})
    if not reply.get("ok"):
        raise ControlSocketError(f"the daemon answered: {clean_text(reply.get('error', '?'), 400)}")
    doc = reply.get("status")
    if not isinstance(doc, dict):
        raise ControlSocketError("the daemon's reply holds no status document")
    return json.dumps(doc, indent=2) if as_json else render_status(doc)


@dataclass
class _Outcome:
    """What a command achieved, filled in as it goes (Ctrl-C may end it anywhere).

    Lines are printed at the end, or at once when ``live`` (a hold in progress).
    """

    exit_code: int = EXIT_NO_DAEMON
    lines: list[str] = field(default_factory=list)
    live: bool = False

    def say(self, line: str, exit_code: int) -> None:
        self.exit_code = exit_code
        if self.live:
            click.echo(line, err=exit_code != EXIT_ACCEPTED)
        else:
            self.lines.append(line)


async def _send(client: ControlClient, name: str, outcome: _Outcome) -> bool:
    """Send one command; record the verdict (with the refusal's reasons); True if accepted."""
    reply = await client.command(name)
    if not reply.get("ok"):
        error = clean_text(reply.get("error", "?"), 400)
        outcome.say(f"{name}: the daemon answered: {error}", EXIT_NO_DAEMON)
        return False
    message = clean_text(reply.get("message", ""), 400)
    if reply.get("accepted") is True:
        outcome.say(f"{name}: accepted" + (f": {message}" if message else ""), EXIT_ACCEPTED)
        return True
    outcome.say(f"{name}: refused" + (f": {message}" if message else ""), EXIT_REFUSED)
    try:
        status_reply = await client.status()
    except ControlSocketError:
        return False
    for reason in as_strings(as_dict(status_reply.get("status")).get("last_refusal")):
        if reason != message:
            outcome.say(f"  - {reason}", EXIT_REFUSED)
    return False


def _report(outcome: _Outcome) -> None:
    for line in outcome.lines:
        click.echo(line, err=outcome.exit_code != EXIT_ACCEPTED)
    sys.exit(outcome.exit_code)


def _command(cli_name: str, op_name: str, help_text: str, unsent_hint: str = "") -> click.Command:
    @_socket_options
    def send(socket_path: str | None, config_name: str | None) -> None:
        path = _socket_path(socket_path, config_name)
        outcome = _Outcome()

        async def main() -> None:
            async with ControlClient(path) as client:
                await _send(client, op_name, outcome)

        try:
            asyncio.run(main())
        except ControlSocketError as exc:
            if unsent_hint:
                click.echo(unsent_hint, err=True)
            _fail(exc)
        _report(outcome)

    return click.command(cli_name, help=help_text)(send)


engage = _command(
    "engage",
    "engage",
    "Engage automatic steering, as the panel's engage button does (READY to ENGAGED).",
)
disengage = _command(
    "disengage",
    "disengage",
    "Hand everything back to the operator (the manual-override button); in ERROR with "
    "the faults cleared, return to READY.",
)
speed_up = _command(
    "speed-up",
    "speed_plus",
    "The + button: raise the set speed one step (from ENGAGED, start speed hold).",
)
speed_down = _command("speed-down", "speed_minus", "The - button: lower the set speed one step.")
estop = _command(
    "estop",
    "estop",
    "Emergency stop: brake fully and latch ESTOP until estop-reset.",
    unsent_hint="THE E-STOP WAS NOT SENT: use the vehicle's e-stop button.",
)
estop_reset = _command(
    "estop-reset",
    "estop_reset",
    "Complete the e-stop reset: leave ESTOP for READY at best (never engaged).",
)


@click.command("hold")
@click.option(
    "--seconds",
    type=click.FloatRange(min=0.0, min_open=True),
    default=5.0,
    show_default=True,
    help="How long to keep the hold-to-move button pressed.",
)
@_socket_options
def hold(seconds: float, socket_path: str | None, config_name: str | None) -> None:
    """Press the hold-to-move button for SECONDS, printing progress, then release it.

    Ctrl-C releases at once; if this command dies without releasing, the daemon releases
    when the connection drops.
    """
    path = _socket_path(socket_path, config_name)
    outcome = _Outcome(live=True)
    try:
        asyncio.run(_hold(path, seconds, outcome))
    except ControlSocketError as exc:
        _fail(exc)
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
    sys.exit(outcome.exit_code)


async def _hold(path: str, seconds: float, outcome: _Outcome) -> None:
    async with ControlClient(path) as client:
        if not await _send(client, "hold", outcome):
            return
        click.echo(f"holding for {seconds:g} s (Ctrl-C releases)")
        loop = asyncio.get_running_loop()
        started_s = loop.time()
        try:
            while (elapsed_s := loop.time() - started_s) < seconds:
                doc = as_dict((await client.status()).get("status"))
                click.echo(f"holding {elapsed_s:4.1f}/{seconds:g} s  {_progress(doc)}")
                await asyncio.sleep(min(HOLD_REPORT_PERIOD_S, seconds - elapsed_s))
        finally:
            if not await _send(client, "release", outcome):
                click.echo(
                    "release was not accepted: the daemon releases when this connection "
                    "closes; use `dbw estop` if the vehicle keeps moving",
                    err=True,
                )


def _progress(doc: dict[str, Any]) -> str:
    parts = [clean_text(doc.get("mode", "?")).upper()]
    speed = speed_line(doc)
    if speed:
        parts.append(speed)
    hold_state = as_dict(doc.get("hold_to_move"))
    if "held" in hold_state:
        parts.append("held" if hold_state.get("held") is True else "not held")
    return "  ".join(parts)


CONTROL_COMMANDS: list[click.Command] = [
    status,
    engage,
    disengage,
    speed_up,
    speed_down,
    estop,
    estop_reset,
    hold,
]
