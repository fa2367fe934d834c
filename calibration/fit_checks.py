"""What every maneuver's fit shares: checking its input columns, counting what it refuses,
and the verdict.

Two kinds of bad input, treated differently on purpose. A *malformed* recording (columns
of different lengths, NaN, two samples at one time, too few samples to say anything) is a
bug upstream or a broken file: :func:`sample_columns` raises ``ValueError`` naming the
column, because a fit that quietly skips it would hide the bug. A well-formed sample that
is no use to the fit (the vehicle was turning, the pedal was still moving, the pot was at
its rail) is normal: the fit refuses it and counts the reason, and :func:`tally` makes
sure each refused sample is counted exactly once, under the first reason that applies,
so the counts add up to the samples refused.

Samples are put in time order first (:func:`time_order`): a recording merged from
several sources need not be, and every fit then gives the same answer for the same
samples whatever order they came in.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from calibration.fit_inputs import same_length, sample_array

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]


@dataclass(frozen=True)
class Verdict:
    """Whether a fit's result may go into the calibration file, and if not, why not."""

    accepted: bool
    reasons: tuple[str, ...] = ()  # every threshold it failed, in words; empty if accepted

    @classmethod
    def from_reasons(cls, reasons: Iterable[str]) -> Verdict:
        refused = tuple(reasons)
        return cls(accepted=not refused, reasons=refused)


def sample_columns(columns: Mapping[str, npt.ArrayLike], min_samples: int) -> dict[str, FloatArray]:
    """The named columns as 1-D float arrays of one length, all finite, at least
    ``min_samples`` long; ValueError (naming the column) otherwise
    (:func:`calibration.fit_inputs.sample_array` checks each)."""
    arrays = {name: sample_array(name, column, min_samples=0) for name, column in columns.items()}
    length = same_length(arrays) if arrays else 0
    if length < min_samples:
        raise ValueError(f"too few samples: {length}, the fit needs at least {min_samples}")
    return arrays


def time_order(arrays: dict[str, FloatArray], time_key: str = "t_s") -> dict[str, FloatArray]:
    """The columns sorted by time (stable); ValueError if two samples share a time."""
    order = np.argsort(arrays[time_key], kind="stable")
    ordered = {name: array[order] for name, array in arrays.items()}
    repeated = np.flatnonzero(np.diff(ordered[time_key]) <= 0.0)
    if repeated.size:
        raise ValueError(
            f"{time_key}: two samples at {ordered[time_key][repeated[0]]} s; each sample "
            "needs its own time (a duplicated or merged recording?)"
        )
    return ordered


def optional_column(
    name: str, column: npt.ArrayLike | None, length: int, default: float
) -> FloatArray:
    """An optional gate's column, or ``default`` everywhere when it was not given."""
    if column is None:
        return np.full(length, default)
    return sample_columns({name: column}, min_samples=0)[name]


def tally(total: int, reasons: Sequence[tuple[str, BoolArray]]) -> tuple[BoolArray, dict[str, int]]:
    """Which samples no reason refuses, and how many each reason refused.

    ``reasons`` are (name, refused-mask) pairs in order of precedence: a sample refused
    for several reasons counts once, under the first. Every name appears in the counts,
    zero or not, so a report always shows the same lines.
    """
    kept = np.ones(total, dtype=np.bool_)
    counts: dict[str, int] = {}
    for name, refused in reasons:
        newly = refused & kept
        counts[name] = counts.get(name, 0) + int(np.count_nonzero(newly))
        kept &= ~refused
    return kept, counts


def runs(mask: BoolArray) -> list[tuple[int, int]]:
    """Half-open index ranges [start, stop) of the consecutive True stretches of ``mask``."""
    padded = np.concatenate(([False], mask, [False])).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def weighted_median(values: FloatArray, weights: FloatArray) -> float:
    """The value that splits the total weight in half (the lower one on a tie)."""
    order = np.argsort(values, kind="stable")
    cumulative = np.cumsum(weights[order])
    index = int(np.searchsorted(cumulative, 0.5 * cumulative[-1]))
    return float(values[order][index])


def mad_sigma(values: FloatArray) -> float:
    """The median absolute deviation scaled to a normal σ (robust to a few outliers)."""
    if values.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(values - np.median(values))))
