"""Probes of the vehicle PC: what Stanley et al.'s memory/storage and system monitors read.

The parsers are pure (text in, numbers out; `ProbeError` for anything else) so they are
tested against any input; `probe_system` does the reading, synchronously: the daemon runs
it in a worker thread with a deadline (`appliance/system_monitor.py`), because a read of
``/sys`` or a ``statvfs`` of a sick disk can block for seconds and the control loop must
never wait for one.

The clocks: the control loop runs on the monotonic clock, which never jumps; the wall
clock can (NTP stepping it, GNSS time arriving, a person with ``date``). `ClockWatch`
compares how far each advanced between two probes and reports a jump, so it is logged
and its effect on wall-clock stamps (log lines, file names) is understood; nothing that
steers reads the wall clock.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

THERMAL_ROOT = Path("/sys/class/thermal")
MAX_PROC_TEXT = 64 * 1024


class ProbeError(ValueError):
    """A probe's source said something that is not what it should say."""


@dataclass(frozen=True)
class SystemHealth:
    """One probe of the PC, stamped with the monotonic time it was taken."""

    measured_s: float
    load_1m: float
    cpu_count: int
    memory_available_mb: float
    memory_total_mb: float
    disk_free_mb: float
    disk_total_mb: float
    temperature_c: float | None  # the hottest readable thermal zone; None: none readable
    wall_clock_jump_s: float  # wall minus monotonic advance since the last probe (0: none)
    probe_duration_s: float


def parse_loadavg(text: str) -> float:
    """The 1-minute load average of ``/proc/loadavg``."""
    fields = text.split()
    if not fields:
        raise ProbeError("empty /proc/loadavg")
    try:
        value = float(fields[0])
    except ValueError as exc:
        raise ProbeError(f"/proc/loadavg: {fields[0][:20]!r} is not a number") from exc
    if not math.isfinite(value) or value < 0:
        raise ProbeError(f"/proc/loadavg: load {value} out of range")
    return value


def parse_meminfo(text: str) -> tuple[float, float]:
    """``(MemAvailable, MemTotal)`` of ``/proc/meminfo`` in megabytes (10^6 bytes)."""
    values: dict[str, float] = {}
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if not sep or key not in ("MemAvailable", "MemTotal"):
            continue
        parts = rest.split()
        if len(parts) != 2 or parts[1] != "kB" or not parts[0].isdigit():
            raise ProbeError(f"/proc/meminfo: {line[:60]!r} is not '<n> kB'")
        values[key] = int(parts[0]) * 1024 / 1e6
    if "MemAvailable" not in values or "MemTotal" not in values:
        raise ProbeError("/proc/meminfo has no MemAvailable or MemTotal")
    return values["MemAvailable"], values["MemTotal"]


def parse_millidegrees(text: str) -> float:
    """A thermal zone's ``temp``: millidegrees Celsius, plausible for a PC."""
    stripped = text.strip()
    try:
        value = int(stripped) / 1000.0
    except ValueError as exc:
        raise ProbeError(f"thermal temp {stripped[:20]!r} is not an integer") from exc
    if not -60.0 <= value <= 200.0:
        raise ProbeError(f"thermal temp {value} degC is not plausible")
    return value


def hottest_zone_c(root: Path = THERMAL_ROOT) -> float | None:
    """The hottest readable thermal zone; None when there is none (containers, VMs)."""
    hottest: float | None = None
    try:
        zones = sorted(root.glob("thermal_zone*/temp"))
    except OSError:
        return None
    for zone in zones:
        try:
            value = parse_millidegrees(zone.read_text(encoding="ascii")[:32])
        except (OSError, UnicodeDecodeError, ProbeError):
            continue
        hottest = value if hottest is None else max(hottest, value)
    return hottest


class ClockWatch:
    """Reports how far the wall clock moved beyond the monotonic one between updates."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._last: tuple[float, float] | None = None

    def update(self, monotonic_s: float, wall_s: float) -> float:
        """The wall clock's jump since the last call (positive: forward); 0 the first time."""
        last, self._last = self._last, (monotonic_s, wall_s)
        if last is None:
            return 0.0
        return (wall_s - last[1]) - (monotonic_s - last[0])


def _read(path: str) -> str:
    with open(path, encoding="ascii") as f:
        return f.read(MAX_PROC_TEXT)


def probe_system(
    disk_path: str,
    clocks: ClockWatch,
    monotonic: Callable[[], float],
    wall: Callable[[], float],
    thermal_root: Path = THERMAL_ROOT,
) -> SystemHealth:
    """Read everything once (blocking: run it off the event loop)."""
    started_s = monotonic()
    load = parse_loadavg(_read("/proc/loadavg"))
    available_mb, total_mb = parse_meminfo(_read("/proc/meminfo"))
    usage = shutil.disk_usage(disk_path)
    temperature = hottest_zone_c(thermal_root)
    measured_s = monotonic()
    jump_s = clocks.update(measured_s, wall())
    return SystemHealth(
        measured_s=measured_s,
        load_1m=load,
        cpu_count=os.cpu_count() or 1,
        memory_available_mb=available_mb,
        memory_total_mb=total_mb,
        disk_free_mb=usage.free / 1e6,
        disk_total_mb=usage.total / 1e6,
        temperature_c=temperature,
        wall_clock_jump_s=jump_s,
        probe_duration_s=measured_s - started_s,
    )
