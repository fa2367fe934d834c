"""What a maneuver's fit says: the verdict, the lines to print, what to merge, a picture.

Kept apart from the steps so the command line (live or ``dbw calibrate fit``) and the
tests read every step's outcome the same way.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from appliance import __version__
from appliance.config.calibration_items import ItemRecord
from appliance.maneuvers.merge import StepResult

Draw = Callable[[Any], Any]  # matplotlib.pyplot -> a figure


@dataclass(frozen=True)
class FitReport:
    """A fit's outcome. ``result`` is what goes into the calibration file, present only
    when the fit was accepted; ``reasons`` says why it was not."""

    step: str
    accepted: bool
    lines: tuple[str, ...]
    reasons: tuple[str, ...] = ()
    result: StepResult | None = None
    draw: Draw | None = None
    figures: Mapping[str, Any] = field(default_factory=dict)  # for --json


def item_record(
    *,
    method: str,
    accepted: bool,
    residual_rms: float,
    residual_max: float,
    residual_unit: str,
    samples_used: int,
    rejected: Mapping[str, int],
    summary: str,
    raw_data: str | None,
    measured_utc: datetime | None = None,
) -> ItemRecord:
    """The calibration file's record of one fit, stamped with this dbw's version."""
    return ItemRecord(
        method=method[:400],
        measured_utc=measured_utc or datetime.now(UTC),
        tool_version=__version__,
        accepted=accepted,
        residual_rms=residual_rms,
        residual_max=residual_max,
        residual_unit=residual_unit,
        samples_used=samples_used,
        rejected={reason[:80]: int(count) for reason, count in rejected.items() if count},
        summary=summary[:400],
        raw_data=None if raw_data is None else raw_data[:400],
    )
