"""Structured logging: JSON lines for the journal, a readable console for a person.

Every event carries the asyncio task that emitted it and a monotonic timestamp, because
on a vehicle the questions are "which service said this" and "how long after the fault
did the brake command go out" — and the wall clock can jump (NTP, GPS time) while the
monotonic clock cannot.
"""

from __future__ import annotations

import asyncio
import json as jsonlib
import logging
import math
import sys
import time
from typing import Any, TextIO

import structlog
from structlog.typing import EventDict, WrappedLogger

LEVELS = ("debug", "info", "warning", "error", "critical")
# What configure_logging chose last, so a child process can log the same way.
_settings: tuple[str, bool] = ("info", False)


def _add_task_and_monotonic(_: WrappedLogger, __: str, event_dict: EventDict) -> EventDict:
    event_dict.setdefault("mono_s", round(time.monotonic(), 6))
    if "task" not in event_dict:
        try:
            task = asyncio.current_task()
        except RuntimeError:
            task = None
        event_dict["task"] = task.get_name() if task is not None else "main"
    return event_dict


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float as its name in a string (``"Infinity"``,
    ``"-Infinity"``, ``"NaN"``, as Python's ``float()`` reads them back)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else jsonlib.dumps(value)
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value


def json_line(event_dict: Any, **kwargs: Any) -> str:
    """One event as strict JSON (RFC 8259).

    Why not plain ``json.dumps``: it writes an age that is infinite (a device never heard
    from) or a NaN as the bare words ``Infinity``/``NaN``, which are not JSON; ``jq``,
    journald's exporters and log shippers then drop or choke on the whole line, the one
    line that says what went wrong. Such a value is written as a string instead.
    """
    try:
        return jsonlib.dumps(event_dict, allow_nan=False, **kwargs)
    except ValueError:
        return jsonlib.dumps(_finite(event_dict), allow_nan=False, **kwargs)


def configure_logging(
    level: str = "info", *, stream: TextIO | None = None, json: bool | None = None
) -> None:
    """Configure structlog once for the process.

    ``json=None`` chooses by whether ``stream`` is a terminal: journald (and any pipe) gets
    one JSON object per line; a person at a terminal gets aligned, coloured text.
    """
    if level not in LEVELS:
        raise ValueError(f"log level must be one of {', '.join(LEVELS)} (got {level!r})")
    out = stream if stream is not None else sys.stdout
    if json is None:
        json = not out.isatty()
    global _settings
    _settings = (level, json)
    renderer: Any = (
        structlog.processors.JSONRenderer(json_line, sort_keys=False)
        if json
        else structlog.dev.ConsoleRenderer(colors=out.isatty())
    )
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            _add_task_and_monotonic,
            structlog.processors.TimeStamper(fmt="iso", utc=True, key="ts"),
            structlog.processors.StackInfoRenderer(),
            structlog.processors.format_exc_info,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(
            logging.getLevelNamesMapping()[level.upper()]
        ),
        logger_factory=structlog.PrintLoggerFactory(file=out),
        cache_logger_on_first_use=False,
    )


def get_logger(name: str) -> structlog.typing.FilteringBoundLogger:
    logger: structlog.typing.FilteringBoundLogger = structlog.get_logger(component=name)
    return logger


def current_log_settings() -> tuple[str, bool]:
    """``(level, json)`` as last configured (a child process is told the same)."""
    return _settings
