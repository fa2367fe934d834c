"""Small helpers to print a figure the same way in every benchmark."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def summarize(name: str, values: Sequence[float], unit: str) -> str:
    data = np.asarray(values, dtype=float)
    if data.size == 0:
        return f"{name}: no samples"
    p50, p99 = np.percentile(data, [50, 99])
    return (
        f"{name}: median {p50:.3f} {unit}, p99 {p99:.3f} {unit}, "
        f"min {data.min():.3f} {unit}, max {data.max():.3f} {unit} (n={data.size})"
    )
