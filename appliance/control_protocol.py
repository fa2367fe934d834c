"""The control socket's protocol, without I/O: request lines in, typed requests out.

Newline-delimited JSON, one reply per request (see :mod:`appliance.control_socket`). Kept
pure so the parser can be fuzzed and tested on its own: a line is a valid request, or it
raises :class:`RequestError` and nothing else.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

COMMAND_NAMES: Final[tuple[str, ...]] = (
    "engage",
    "disengage",
    "speed_plus",
    "speed_minus",
    "estop",
    "estop_reset",
    "hold",
    "release",
)
OPS: Final[tuple[str, ...]] = ("status", "command", "route", "maneuver", "samples")
MANEUVER_ACTIONS: Final[tuple[str, ...]] = ("start", "stop")
MAX_MANEUVER_NAME: Final = 32
# A reply is encoded in the event loop: 200 samples take about a millisecond.
MAX_SAMPLES_LIMIT: Final = 200
MAX_ROUTE_NAME: Final = 64
MAX_LINE_BYTES: Final = 8 * 1024


class ControlSocketError(Exception):
    """The client cannot talk to the daemon; the message says why and what to do."""


class RequestError(Exception):
    """A request line that is not a valid request; the message becomes the error reply."""


# ---------------------------------------------------------------- the protocol (no I/O)


@dataclass(frozen=True)
class StatusRequest:
    pass


@dataclass(frozen=True)
class CommandRequest:
    name: str


@dataclass(frozen=True)
class RouteRequest:
    """Select the route the `route` autopilot follows (the paper's GUI did this)."""

    select: str


@dataclass(frozen=True)
class ManeuverRequest:
    """Start or stop the tap of a calibration maneuver (`dbw calibrate STEP`)."""

    action: str
    step: str


@dataclass(frozen=True)
class SamplesRequest:
    """The tapped samples from sequence number ``since`` on, at most ``limit``."""

    since: int
    limit: int = MAX_SAMPLES_LIMIT


Request = StatusRequest | CommandRequest | RouteRequest | ManeuverRequest | SamplesRequest

_FIELDS: Final[dict[str, frozenset[str]]] = {
    "status": frozenset({"op"}),
    "command": frozenset({"op", "name"}),
    "route": frozenset({"op", "select"}),
    "maneuver": frozenset({"op", "action", "step"}),
    "samples": frozenset({"op", "since", "limit"}),
}


def decode_request(line: bytes) -> Request:
    """Parse one request line (with or without its newline); raise only RequestError."""
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError:
        raise RequestError("request is not UTF-8 text") from None
    if not text.strip():
        raise RequestError('empty request: send one JSON object per line, e.g. {"op": "status"}')
    try:
        message = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise RequestError(f"request is not valid JSON: {exc}") from None
    if not isinstance(message, dict):
        raise RequestError(
            f'request must be a JSON object, got {type(message).__name__}: e.g. {{"op": "status"}}'
        )
    op = message.get("op")
    if op not in OPS:
        what = "missing 'op'" if "op" not in message else f"unknown op {_short(op)}"
        raise RequestError(f"{what}: known ops are {', '.join(OPS)}")
    assert isinstance(op, str)
    unknown = sorted(set(message) - _FIELDS[op])
    if unknown:
        raise RequestError(
            f"unknown field(s) for op {op!r}: {', '.join(_short(key) for key in unknown)} "
            f"(known: {', '.join(sorted(_FIELDS[op]))})"
        )
    if op == "status":
        return StatusRequest()
    if op == "route":
        select = message.get("select")
        if not isinstance(select, str) or not 0 < len(select) <= MAX_ROUTE_NAME:
            raise RequestError(
                f"route needs 'select': a route name of 1 to {MAX_ROUTE_NAME} characters, "
                f"got {_short(select)}"
            )
        return RouteRequest(select)
    if op == "maneuver":
        return _maneuver(message)
    if op == "samples":
        return _samples(message)
    name = message.get("name")
    if name not in COMMAND_NAMES:
        what = (
            "missing command 'name'" if "name" not in message else f"unknown command {_short(name)}"
        )
        raise RequestError(f"{what}: known commands are {', '.join(COMMAND_NAMES)}")
    assert isinstance(name, str)
    return CommandRequest(name)


def _maneuver(message: Mapping[str, Any]) -> ManeuverRequest:
    action, step = message.get("action"), message.get("step")
    if action not in MANEUVER_ACTIONS:
        raise RequestError(
            f"maneuver needs 'action': one of {', '.join(MANEUVER_ACTIONS)}, got {_short(action)}"
        )
    if not isinstance(step, str) or not 0 < len(step) <= MAX_MANEUVER_NAME:
        raise RequestError(
            f"maneuver needs 'step': a name of 1 to {MAX_MANEUVER_NAME} characters, "
            f"got {_short(step)}"
        )
    assert isinstance(action, str)
    return ManeuverRequest(action, step)


def _samples(message: Mapping[str, Any]) -> SamplesRequest:
    since, limit = message.get("since"), message.get("limit", MAX_SAMPLES_LIMIT)
    # bool is an int in Python; a JSON true is not a sequence number.
    if not isinstance(since, int) or isinstance(since, bool) or not 0 <= since < 2**63:
        raise RequestError(f"samples needs 'since': a sequence number >= 0, got {_short(since)}")
    if not isinstance(limit, int) or isinstance(limit, bool) or not 1 <= limit <= MAX_SAMPLES_LIMIT:
        raise RequestError(f"samples 'limit' must be 1..{MAX_SAMPLES_LIMIT}, got {_short(limit)}")
    return SamplesRequest(since, limit)


def encode_message(message: Mapping[str, Any]) -> bytes:
    """One line of strict JSON: non-finite numbers become null, anything else odd a string."""
    return json.dumps(_jsonable(message), allow_nan=False, separators=(",", ":")).encode() + b"\n"


def decode_reply(line: bytes) -> dict[str, Any]:
    """Parse one reply line; raise only ControlSocketError."""
    try:
        reply = json.loads(line.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise ControlSocketError("the daemon sent a reply that is not JSON") from None
    if not isinstance(reply, dict) or not isinstance(reply.get("ok"), bool):
        raise ControlSocketError("the daemon sent a reply this client does not understand")
    return reply


def error_reply(error: str) -> dict[str, Any]:
    return {"ok": False, "error": error}


def _jsonable(value: Any) -> Any:
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(key): _jsonable(item) for key, item in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [_jsonable(item) for item in value]
    return str(value)


def _short(value: object, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
