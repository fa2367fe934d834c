"""`dbw status`, `dbw engage`, `dbw hold`, ...: the daemon's state and bench commands.

They talk to the running daemon over its local control socket (see
:mod:`appliance.control_socket`). Exit status: 0 the daemon accepted, 1 it refused (its
reasons are printed), 2 there is no talking to it (no daemon, no permission, bad config).
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NoReturn

import click

from appliance.config import BUILTIN_PROFILES, ConfigError, load_config
from appliance.control_socket import ControlClient, ControlSocketError, query_sync

EXIT_ACCEPTED = 0
EXIT_REFUSED = 1
EXIT_NO_DAEMON = 2
HOLD_REPORT_PERIOD_S = 0.5

_CONFIG_HELP = (
    "Take the socket path (paths.control_socket) from this TOML file or built-in profile ("
    + ", ".join(BUILTIN_PROFILES)
    + "). Default: sim."
)


# ---------------------------------------------------------------- rendering (pure)


def render_status(doc: dict[str, Any]) -> str:
    """A compact human view of the daemon's status document.

    Every key is optional and may hold anything: what is there and makes sense is shown,
    nothing here raises.
    """
    if not isinstance(doc, dict):
        doc = {}
    lines = [_headline(doc)]
    speed = _speed_line(doc)
    if speed:
        lines.append(speed)
    hold = _dict(doc.get("hold_to_move"))
    if hold.get("required") is True:
        held = "held" if hold.get("held") is True else "not held"
        lines.append(f"hold-to-move: required, {held}")
    if doc.get("estop_latched") is True:
        lines.append("E-STOP LATCHED: `dbw estop-reset` once the vehicle is safe")
    refusals = _strings(doc.get("last_refusal"))
    if refusals:
        lines.append("last refusal:")
        lines += [f"  - {reason}" for reason in refusals]
    lines += _faults(doc)
    lines += _inputs(doc)
    lines += _name_table("commands", doc.get("commands"))
    overrides = _dict(doc.get("overrides"))
    if overrides:
        active = [_text(name) for name, on in overrides.items() if on is True]
        lines.append("overrides: " + (", ".join(active) if active else "none"))
    loop = _loop_line(doc)
    if loop:
        lines.append(loop)
    event_loop = _event_loop_line(doc)
    if event_loop:
        lines.append(event_loop)
    lines += _name_table("services", doc.get("services"))
    return "\n".join(lines)


def _headline(doc: dict[str, Any]) -> str:
    mode = _text(doc.get("mode")).upper() if doc.get("mode") is not None else ""
    head = mode or "UNKNOWN MODE"
    since_s = _finite(doc.get("mode_since_s"))
    if since_s is not None:
        head += f" for {format_duration(since_s)}"
    about = []
    if doc.get("vehicle") is not None:
        about.append(f"vehicle {_text(doc.get('vehicle'))}")
    uptime_s = _finite(doc.get("uptime_s"))
    if uptime_s is not None:
        about.append(f"up {format_duration(uptime_s)}")
    return head + (f"  ({', '.join(about)})" if about else "")


def _speed_line(doc: dict[str, Any]) -> str:
    set_mps = _finite(doc.get("set_speed_mps"))
    measured_mps = _finite(doc.get("measured_speed_mps"))
    parts = []
    if "set_speed_mps" in doc:
        parts.append(f"set {set_mps:.2f} m/s" if set_mps is not None else "set -")
    if measured_mps is not None:
        parts.append(f"measured {measured_mps:.2f} m/s")
    return "speed: " + ", ".join(parts) if parts else ""


def _faults(doc: dict[str, Any]) -> list[str]:
    lines = []
    if "faults" in doc:
        faults = [_dict(fault) for fault in _list(doc.get("faults"))]
        if not isinstance(doc.get("faults"), list):
            lines.append(f"faults: unreadable ({_text(doc.get('faults'), 40)})")
        elif not faults:
            lines.append("faults: none")
        else:
            lines.append(f"faults ({len(faults)}):")
            for fault in faults:
                line = f"  {_text(fault.get('key', '?'))}"
                if fault.get("detail"):
                    line += f": {_text(fault.get('detail'))}"
                age_s = _finite(fault.get("since_s"))
                if age_s is not None:
                    line += f" (for {format_duration(age_s)})"
                lines.append(line)
    history = [_dict(entry) for entry in _list(doc.get("fault_history"))]
    if history:
        latest = history[-1]
        lines.append(
            f"fault history: {len(history)} cleared, latest {_text(latest.get('key', '?'))}"
        )
    return lines


def _inputs(doc: dict[str, Any]) -> list[str]:
    inputs = _dict(doc.get("inputs"))
    if not inputs:
        return []
    rows = []
    for name, raw in inputs.items():
        entry = _dict(raw)
        age = entry.get("age_s", "?")
        age_s = _finite(age)
        if age is None or (_number(age) is not None and age_s is None):
            age_text = "never"  # null or infinite: nothing has arrived yet
        else:
            age_text = format_duration(age_s) if age_s is not None else "?"
        limit_s = _finite(entry.get("limit_s"))
        flags = []
        if entry.get("stale") is True:
            flags.append("STALE")
        if entry.get("critical") is True:
            flags.append("critical")
        rows.append(
            (
                _text(name),
                age_text,
                format_duration(limit_s) if limit_s is not None else "-",
                " ".join(flags),
            )
        )
    width = min(max(5, *(len(row[0]) for row in rows)), 32)
    lines = [f"inputs:{'':{width - 5}} {'age':>8} {'limit':>8}"]
    for name, age_text, limit_text, flags_text in rows:
        lines.append(f"  {name:<{width}} {age_text:>8} {limit_text:>8}  {flags_text}".rstrip())
    return lines


def _name_table(title: str, value: object) -> list[str]:
    table = _dict(value)
    if not table:
        return []
    width = min(max(len(_text(name)) for name in table), 24)
    return [f"{title}:"] + [
        f"  {_text(name):<{width}}  {_text(item)}" for name, item in table.items()
    ]


def _loop_line(doc: dict[str, Any]) -> str:
    loop = _dict(doc.get("loop"))
    parts = []
    for key, template in (
        ("rate_hz", "{:.1f} Hz"),
        ("cycles", "{:.0f} cycles"),
        ("overruns", "{:.0f} overruns"),
        ("jitter_p99_ms", "jitter p99 {:.2f} ms"),
        ("step_p99_ms", "step p99 {:.2f} ms"),
    ):
        value = _finite(loop.get(key))
        if value is not None:
            parts.append(template.format(value))
    wakes_by = loop.get("wakes_by")
    if isinstance(wakes_by, str) and parts:
        parts.append(f"wakes by {_text(wakes_by)}")
    deferred = _finite(loop.get("work_deferred"))
    if deferred is not None and parts:
        parts.append(f"{deferred:.0f} deferred for a cycle")
    return "loop: " + ", ".join(parts) if parts else ""


def _event_loop_line(doc: dict[str, Any]) -> str:
    """Who held the event loop longest, in the last window and since start."""
    lag = _dict(doc.get("event_loop"))
    disabled = _dict(lag.get("since_start")).get("disabled")
    if disabled:
        return f"event loop: not monitored: {_text(disabled)}"
    longest = _finite(lag.get("longest_callback_ms"))
    if longest is None:
        return ""
    by = _text(lag.get("longest_callback_by"))
    line = f"event loop: longest callback {longest:.1f} ms ({by})"
    window = _finite(lag.get("window_s"))
    slow = _finite(lag.get("slow_callbacks"))
    busy = _finite(lag.get("busy_pct"))
    if window is not None and slow is not None:
        line += f", {slow:.0f} slow in the last {window:.1f} s"
    cpu = _finite(lag.get("cpu_pct"))
    if busy is not None:
        line += f", {busy:.0f} % busy"
        if cpu is not None:
            line += f" ({cpu:.0f} % CPU)"
    worst = _dict(lag.get("since_start"))
    worst_ms = _finite(worst.get("longest_callback_ms"))
    if worst_ms is not None:
        line += f"; worst since start {worst_ms:.1f} ms ({_text(worst.get('longest_callback_by'))})"
    return line


def format_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "never"
    if abs(seconds) < 1.0:
        return f"{seconds * 1e3:.0f} ms"
    if abs(seconds) < 120.0:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(int(seconds), 60)
    if minutes < 120:
        return f"{minutes} min {secs} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes} min"


def _number(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        return float(value)
    except OverflowError:  # an integer too large for a float
        return math.inf if value > 0 else -math.inf


def _finite(value: object) -> float | None:
    number = _number(value)
    return number if number is not None and math.isfinite(number) else None


def _dict(value: object) -> dict[Any, Any]:
    return value if isinstance(value, dict) else {}


def _list(value: object) -> list[Any]:
    return value if isinstance(value, list) else []


def _strings(value: object) -> list[str]:
    if value is None or value == "" or value == []:
        return []
    items = value if isinstance(value, list) else [value]
    return [_text(item) for item in items]


def _text(value: object, limit: int = 160) -> str:
    """One printable line (the daemon's strings may hold anything, even escape codes)."""
    if not isinstance(value, str):
        try:
            value = json.dumps(value, default=str)
        except (TypeError, ValueError, RecursionError):
            value = "?"
    text = "".join(ch if ch.isprintable() else "?" for ch in value[: limit + 1])
    return text if len(text) <= limit else text[: limit - 3] + "..."


# ---------------------------------------------------------------- the commands


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


def _socket_path(socket_path: str | None, config_name: str | None) -> str:
    if socket_path:
        return socket_path
    if config_name is None:
        config_name = os.environ.get("DBW_CONFIG") or (
            INSTALLED_CONFIG if os.path.exists(INSTALLED_CONFIG) else None
        )
    try:
        return load_config(config_name).paths.control_socket
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
        raise ControlSocketError(f"the daemon answered: {_text(reply.get('error', '?'), 400)}")
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
        error = _text(reply.get("error", "?"), 400)
        outcome.say(f"{name}: the daemon answered: {error}", EXIT_NO_DAEMON)
        return False
    message = _text(reply.get("message", ""), 400)
    if reply.get("accepted") is True:
        outcome.say(f"{name}: accepted" + (f": {message}" if message else ""), EXIT_ACCEPTED)
        return True
    outcome.say(f"{name}: refused" + (f": {message}" if message else ""), EXIT_REFUSED)
    try:
        status_reply = await client.status()
    except ControlSocketError:
        return False
    for reason in _strings(_dict(status_reply.get("status")).get("last_refusal")):
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
                doc = _dict((await client.status()).get("status"))
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
    parts = [_text(doc.get("mode", "?")).upper()]
    speed = _speed_line(doc)
    if speed:
        parts.append(speed)
    hold_state = _dict(doc.get("hold_to_move"))
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
