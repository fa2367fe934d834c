"""The system monitor service: probes the PC once a period, off the event loop.

Each probe (`drivers/system/probes.py`) runs in a worker thread: a read of ``/sys`` or a
``statvfs`` of a failing disk may block for seconds, and the control loop must never wait
on one. A probe still running after ``probe_timeout_s`` is logged as stuck and no second
one is started beside it; its sample ages meanwhile, and the core treats a monitor older
than ``max_age_s`` as not reporting (`safety/system_health.py`). Each sample is published
on ``system.health``, which the core reads as an input and the recorder records; crossing
a warning level, and any wall-clock jump, is logged once when it happens.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from appliance.config import VehicleConfig
from appliance.logs import get_logger
from appliance.supervisor import ServiceContext
from drivers.system.probes import ClockWatch, ProbeError, SystemHealth, probe_system
from drivers.topics import Topic

log = get_logger("system")

SYSTEM_HEALTH_TOPIC = "system.health"

Probe = Callable[[str, ClockWatch, Callable[[], float], Callable[[], float]], SystemHealth]


def disk_path(config: VehicleConfig) -> str:
    """The monitored file system: where the state (logs, recordings) goes, or the nearest
    existing directory above it (the state directory may not exist yet)."""
    path = Path(config.system_monitor.disk_path or config.paths.state_dir).absolute()
    for candidate in (path, *path.parents):
        if candidate.exists():
            return str(candidate)
    return "/"


class SystemMonitor:
    def __init__(
        self,
        config: VehicleConfig,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        probe: Probe = probe_system,
    ) -> None:
        self.params = config.system_monitor
        self.path = disk_path(config)
        self.topic: Topic[SystemHealth] = Topic(SYSTEM_HEALTH_TOPIC)
        self._clock = clock
        self._wall = wall
        self._probe = probe
        self._clocks = ClockWatch()
        self._pending: asyncio.Future[SystemHealth] | None = None
        self._pending_since_s = 0.0
        self._warned: set[str] = set()
        self.problem = ""
        self.clock_jumps = 0

    async def run(self, ctx: ServiceContext) -> None:
        loop = asyncio.get_running_loop()
        self._clocks.reset()
        while True:
            if self._pending is None:
                self._pending = loop.run_in_executor(None, self._probe_once)
                self._pending_since_s = self._clock()
            pending = self._pending
            done, _ = await asyncio.wait({pending}, timeout=self.params.probe_timeout_s)
            if done:
                self._pending = None
                self._take(pending)
            else:
                stuck_s = self._clock() - self._pending_since_s
                self._set_problem(f"probe stuck for {stuck_s:.1f} s")
            ctx.beat()
            await asyncio.sleep(self.params.period_s)

    def _probe_once(self) -> SystemHealth:
        return self._probe(self.path, self._clocks, self._clock, self._wall)

    def _take(self, done: asyncio.Future[SystemHealth]) -> None:
        try:
            health = done.result()
        except (ProbeError, OSError) as exc:
            self._set_problem(f"probe failed: {exc}")
            return
        self._set_problem("")
        self.topic.publish(health, health.measured_s)
        self._warn(health)

    def _set_problem(self, problem: str) -> None:
        if problem and problem.split(":")[0] != self.problem.split(":")[0]:
            log.warning("system_probe_problem", problem=problem)
        elif not problem and self.problem:
            log.info("system_probe_recovered", after=self.problem)
        self.problem = problem

    def _warn(self, health: SystemHealth) -> None:
        p = self.params
        if abs(health.wall_clock_jump_s) > p.clock_jump_warn_s:
            self.clock_jumps += 1
            log.warning(
                "wall_clock_jump",
                jump_s=round(health.wall_clock_jump_s, 3),
                note="the control loop runs on the monotonic clock and is not affected",
            )
        self._crossing(
            "disk_low",
            health.disk_free_mb < p.disk_warn_free_mb,
            free_mb=round(health.disk_free_mb),
            path=self.path,
        )
        self._crossing(
            "temperature_high",
            health.temperature_c is not None and health.temperature_c > p.temperature_warn_c,
            temperature_c=health.temperature_c,
        )

    def _crossing(self, name: str, now_over: bool, **fields: Any) -> None:
        if now_over and name not in self._warned:
            self._warned.add(name)
            log.warning(f"system_{name}", **fields)
        elif not now_over and name in self._warned:
            self._warned.discard(name)
            log.info(f"system_{name}_cleared", **fields)

    def status(self, now_s: float) -> dict[str, Any]:
        sample = self.topic.latest()
        doc: dict[str, Any] = {"problem": self.problem, "clock_jumps": self.clock_jumps}
        if sample is not None:
            h = sample.value
            doc.update(
                age_s=round(now_s - sample.stamp_s, 3),
                load_1m=h.load_1m,
                cpu_count=h.cpu_count,
                memory_available_mb=round(h.memory_available_mb),
                disk_free_mb=round(h.disk_free_mb),
                disk_path=self.path,
                temperature_c=h.temperature_c,
            )
        return doc
