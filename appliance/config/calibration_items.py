"""Where each number in a calibration file came from: one record per maneuver's result.

Why: a calibration file is trusted for months on a nine-ton vehicle. When the vehicle
drifts off its line, the first question is how each number was obtained: by which method,
when, with which version of the tool, how well the fit matched its data, whether it was
accepted, and from which raw data it can be fitted again (``dbw calibrate fit``). The
records sit under ``[items.<name>]``, optional like every table added after version 1:
a file written by hand, or before the maneuvers existed, has none and still loads.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, field_validator

ITEM_NAMES = ("pot_centre", "pot_map", "palm_tree", "k_ratio", "lookahead", "pedals")
Count = Annotated[int, Field(ge=0)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class ItemRecord(_Model):
    """How one item was measured, and how well."""

    method: str = Field(min_length=1, max_length=400)
    measured_utc: AwareDatetime
    tool_version: str = Field(min_length=1, max_length=40)
    accepted: bool
    residual_rms: float = Field(ge=0.0, allow_inf_nan=False)
    residual_max: float = Field(ge=0.0, allow_inf_nan=False)
    residual_unit: str = Field(min_length=1, max_length=20)  # e.g. "deg tyre", "counts"
    samples_used: Count
    rejected: dict[str, Count] = Field(default_factory=dict)  # reason -> samples refused
    summary: str = Field("", max_length=400)
    raw_data: str | None = Field(None, max_length=400)  # the samples file or the recording

    @field_validator("measured_utc")
    @classmethod
    def _in_utc(cls, value: datetime) -> datetime:
        if value.utcoffset() != UTC.utcoffset(None):
            raise ValueError(f"measured_utc must be in UTC, ending in Z (got {value.isoformat()})")
        return value.replace(tzinfo=UTC)

    @field_validator("rejected")
    @classmethod
    def _reasons_named(cls, value: dict[str, int]) -> dict[str, int]:
        for reason in value:
            if not 0 < len(reason) <= 80:
                raise ValueError(f"a rejection reason must be 1..80 characters (got {reason!r})")
        return value


class CalibrationItems(_Model):
    """One optional record per maneuver (``dbw calibrate STEP`` writes its own)."""

    pot_centre: ItemRecord | None = None
    pot_map: ItemRecord | None = None
    palm_tree: ItemRecord | None = None
    k_ratio: ItemRecord | None = None
    lookahead: ItemRecord | None = None
    pedals: ItemRecord | None = None
