"""A maneuver's samples out of the flight recording: replay taps the same cycles again.

Why: the samples file may be lost (the technician's laptop), but the vehicle's recorder
kept every input and the tap's start and stop as requests. Replaying the recording's
session through the recorded core re-runs the tap over the same cycles, so the samples
come back exactly as the daemon gave them (``appliance.core.maneuver_tap``), and
``dbw calibrate fit RECORDING.mcap`` fits them like a samples file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from appliance.core.maneuver_tap import ManeuverSample
from appliance.recording.reader import RecordingReader, session_files
from appliance.recording.replay import Replayer, ReplayError, core_from_metadata


class RecordingSamplesError(Exception):
    """No maneuver's samples can be had from the recording; the message says why."""


@dataclass
class TappedRun:
    """One maneuver's run as the replayed tap saw it."""

    step: str
    samples: list[dict[str, Any]] = field(default_factory=list)


def tapped_runs(path: Path) -> tuple[str, list[TappedRun]]:
    """The vehicle's name and every maneuver run in the recording session ending with
    ``path`` (its earlier files replayed first), in order."""
    files = session_files(path)
    first = RecordingReader(files[0])
    metadata = first.read_metadata()
    if not metadata:
        problems = "; ".join(first.report.problems) or "no metadata"
        raise RecordingSamplesError(f"{files[0]}: not a recording ({problems})")
    try:
        core = core_from_metadata(metadata)
    except ReplayError as exc:
        raise RecordingSamplesError(f"{files[0]}: {exc}") from None
    tap = core.maneuver
    runs: list[TappedRun] = []

    def listen(sample: ManeuverSample) -> None:
        if sample.seq == tap.first_seq or not runs:
            runs.append(TappedRun(str(tap.step)))
        runs[-1].samples.append(sample.as_dict())

    tap.listeners.append(listen)
    replayer = Replayer(core)
    try:
        for file in files:
            replayer.feed_file(file)
    except ReplayError as exc:
        raise RecordingSamplesError(f"replay stopped: {exc}") from None
    return core.config.name, runs


def maneuver_samples(path: Path, step: str | None = None) -> tuple[str, TappedRun]:
    """The vehicle's name and the last run (of ``step``, if given) in the recording."""
    vehicle, runs = tapped_runs(path)
    wanted = [run for run in runs if step is None or run.step == step]
    if not wanted:
        seen = ", ".join(sorted({run.step for run in runs})) or "none"
        what = "no maneuver" if step is None else f"no {step} maneuver"
        raise RecordingSamplesError(f"{path}: {what} in the recording (maneuvers in it: {seen})")
    return vehicle, wanted[-1]
