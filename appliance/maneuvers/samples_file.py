"""A maneuver's raw samples on disk: JSON lines, a header first, appended as they arrive.

Why a file of its own beside the recording: the technician's run must survive the things
that end it early (Ctrl-C, an override, a dropped connection, a dead laptop battery) and
resume where it stopped; a line appended per sample loses at most the line being written.
The same file is what ``dbw calibrate fit FILE`` fits again offline, and what the
calibration file's record names as the raw data. The recorder keeps the same cycles in
the MCAP recording (the tap's start and stop are recorded requests), so the recording is
a second, independent source of the same samples.

A damaged file is refused with the line number and what is wrong, except a torn last
line (the write a crash interrupted), which is dropped and reported.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Final

from appliance.core.maneuver_tap import STEPS, ManeuverSample

FORMAT: Final = "dbw-maneuver-samples"
FORMAT_VERSION: Final = 1
SAMPLE_FIELDS: Final = frozenset(ManeuverSample.__dataclass_fields__)


class SamplesFileError(Exception):
    """A samples file that cannot be used; the message names the file and the line."""


@dataclass
class SamplesFile:
    """What a samples file holds: its header and its samples, in order."""

    step: str
    vehicle: str
    header: dict[str, Any]
    samples: list[dict[str, Any]] = field(default_factory=list)
    torn_last_line: bool = False


def header(step: str, vehicle: str, tool_version: str, started_utc: str) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "step": step,
        "vehicle": vehicle,
        "tool_version": tool_version,
        "started_utc": started_utc,
    }


class SamplesWriter:
    """Appends samples to a new or resumed file, one flushed line each."""

    def __init__(self, path: Path, first_header: Mapping[str, Any] | None) -> None:
        self.path = path
        self._file: IO[str] = path.open("a", encoding="utf-8")
        if first_header is not None:
            self._write(first_header)

    def append(self, samples: Iterable[Mapping[str, Any]]) -> None:
        for sample in samples:
            self._write(sample)
        self._file.flush()

    def mark(self, event: str, **fields: Any) -> None:
        """A run boundary (started, resumed, stopped, aborted): fits see a gap there."""
        self._write({"event": event, **fields})
        self._file.flush()

    def close(self) -> None:
        self._file.close()

    def _write(self, record: Mapping[str, Any]) -> None:
        self._file.write(json.dumps(record, allow_nan=False, separators=(",", ":")) + "\n")


def read_samples_file(path: str | Path, vehicle: str | None = None) -> SamplesFile:
    """Read and check a samples file; ``vehicle`` (if given) must be the one it was taken on."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").split("\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise SamplesFileError(f"{path}: cannot read the samples file: {exc}") from None
    torn = bool(lines and lines[-1])  # a complete file ends with a newline
    records: list[tuple[int, Any]] = []
    for number, line in enumerate(lines, start=1):
        if not line:
            continue
        try:
            records.append((number, json.loads(line)))
        except ValueError as exc:
            if torn and number == len(lines):
                break  # the last write, interrupted: everything before it is whole
            raise SamplesFileError(f"{path}:{number}: not a JSON line ({exc})") from None
    else:
        torn = False
    if not records:
        raise SamplesFileError(f"{path}: empty: not a maneuver's samples file")
    number, first = records[0]
    if not isinstance(first, dict) or first.get("format") != FORMAT:
        raise SamplesFileError(f"{path}:1: not a maneuver's samples file (no {FORMAT} header)")
    if first.get("version") != FORMAT_VERSION:
        raise SamplesFileError(
            f"{path}:1: samples file version {first.get('version')!r}; this dbw reads "
            f"version {FORMAT_VERSION}"
        )
    step, taken_on = first.get("step"), first.get("vehicle")
    if step not in STEPS or not isinstance(taken_on, str):
        raise SamplesFileError(f"{path}:1: header names no known step and vehicle: {first}")
    if vehicle is not None and taken_on != vehicle:
        raise SamplesFileError(
            f"{path}: taken on vehicle {taken_on!r}, not {vehicle!r}: fit it with that "
            "vehicle's config"
        )
    result = SamplesFile(str(step), taken_on, first, torn_last_line=torn)
    for number, record in records[1:]:
        if not isinstance(record, dict):
            raise SamplesFileError(f"{path}:{number}: a sample must be a JSON object")
        if "event" in record:
            continue
        missing = SAMPLE_FIELDS - set(record)
        if missing:
            raise SamplesFileError(f"{path}:{number}: sample lacks {', '.join(sorted(missing))}")
        t_s = record["t_s"]
        if not isinstance(t_s, int | float) or not math.isfinite(t_s):
            raise SamplesFileError(f"{path}:{number}: t_s must be a number, got {t_s!r}")
        result.samples.append(record)
    return result
