"""Checks every fit makes of its inputs, and the counters of what it rejected.

A fit takes plain arrays from a recording. Garbage there (a wrong shape, a NaN, arrays of
different lengths, too few samples) is a bug or a broken recording, not a measurement to
weigh, so it raises ``ValueError`` naming the array and the problem; only *valid* samples
that do not qualify (the vehicle stood, the fix was poor) are rejected and counted.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IndexArray = npt.NDArray[np.intp]


def sample_array(name: str, values: npt.ArrayLike, *, min_samples: int = 1) -> FloatArray:
    """``values`` as a 1-D float array of finite numbers, at least ``min_samples`` long."""
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} is not an array of numbers ({exc})") from None
    if array.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional (got shape {array.shape})")
    if array.size < min_samples:
        raise ValueError(f"{name} has {array.size} samples, the fit needs at least {min_samples}")
    bad = np.flatnonzero(~np.isfinite(array))
    if bad.size:
        raise ValueError(
            f"{name} holds {bad.size} non-finite value(s) (first at index {bad[0]}): "
            "drop or repair those samples before fitting"
        )
    return array


def same_length(arrays: Mapping[str, FloatArray]) -> int:
    """The common length of ``arrays``; ValueError naming each length when they differ."""
    lengths = {name: array.size for name, array in arrays.items()}
    if len(set(lengths.values())) > 1:
        listed = ", ".join(f"{name} {n}" for name, n in lengths.items())
        raise ValueError(f"sample arrays differ in length: {listed}")
    return next(iter(lengths.values()))


def strictly_increasing(name: str, t_s: FloatArray) -> None:
    """Time stamps must increase: a repeated or reversed stamp means a broken recording."""
    steps = np.diff(t_s)
    bad = np.flatnonzero(steps <= 0.0)
    if bad.size:
        raise ValueError(
            f"{name} must increase strictly (it does not at index {bad[0] + 1}: "
            f"{t_s[bad[0]]!r} then {t_s[bad[0] + 1]!r})"
        )


def positive(name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a positive number (got {value!r})")


def count(rejected: dict[str, int], reason: str, n: int = 1) -> None:
    """Add ``n`` rejections for ``reason`` (nothing when ``n`` is 0, so no empty keys)."""
    if n:
        rejected[reason] = rejected.get(reason, 0) + n
