"""The PC's own health as faults: a full disk, an overheated PC, memory running out, or a
system monitor that stopped reporting (deny by default: what cannot be seen is not fine).

Plain numbers in, faults out: the probes are a driver's business (`drivers/system/`),
the thresholds the vehicle file's (`[system_monitor]`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class SystemHealthParams:
    max_age_s: float
    disk_stop_free_mb: float
    temperature_max_c: float
    memory_min_available_mb: float


def system_faults(
    params: SystemHealthParams,
    age_s: float,
    disk_free_mb: float | None,
    temperature_c: float | None,
    memory_available_mb: float | None,
) -> dict[str, str]:
    """Fault key -> reason; empty when the PC is fit to drive."""
    if not (math.isfinite(age_s) and age_s <= params.max_age_s):
        shown = "never reported" if not math.isfinite(age_s) else f"{age_s:.1f} s old"
        return {"stale:system.health": f"system monitor {shown} (limit {params.max_age_s} s)"}
    faults: dict[str, str] = {}
    if disk_free_mb is not None and not disk_free_mb >= params.disk_stop_free_mb:
        limit = params.disk_stop_free_mb
        faults["system:disk_full"] = (
            f"disk nearly full: {disk_free_mb:.0f} MB free (limit {limit:.0f} MB)"
        )
    if temperature_c is not None and not temperature_c <= params.temperature_max_c:
        faults["system:overheated"] = (
            f"PC overheated: {temperature_c:.0f} degC (limit {params.temperature_max_c:.0f} degC)"
        )
    if memory_available_mb is not None and not (
        memory_available_mb >= params.memory_min_available_mb
    ):
        faults["system:memory_low"] = (
            f"memory nearly exhausted: {memory_available_mb:.0f} MB available "
            f"(limit {params.memory_min_available_mb:.0f} MB)"
        )
    return faults
