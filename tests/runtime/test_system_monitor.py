"""The system monitor service: a stuck probe never holds up the event loop.

The probe is replaced by one the test controls: it can block (a hung ``statvfs``), fail,
or answer. The service must keep beating, start no second probe beside a stuck one, say
the probe is stuck, and publish again once the probe answers; the event loop meanwhile
runs a ticker undisturbed.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable

from appliance.config import load_config
from appliance.system_monitor import SystemMonitor
from drivers.system.probes import ClockWatch, ProbeError, SystemHealth


class _Ctx:
    name = "system_monitor"

    def __init__(self) -> None:
        self.beats = 0

    def beat(self) -> None:
        self.beats += 1


class ControlledProbe:
    def __init__(self) -> None:
        self.release = threading.Event()
        self.calls = 0
        self.fail = False

    def __call__(
        self,
        path: str,
        clocks: ClockWatch,
        monotonic: Callable[[], float],
        wall: Callable[[], float],
    ) -> SystemHealth:
        self.calls += 1
        if not self.release.wait(10.0):
            raise ProbeError("the test never released the probe")
        if self.fail:
            raise ProbeError("/proc/meminfo has no MemAvailable or MemTotal")
        now = monotonic()
        return SystemHealth(now, 0.1, 2, 1000.0, 2000.0, 9000.0, 10000.0, None, 0.0, 0.0)


def test_a_stuck_probe_is_reported_and_never_blocks_the_loop() -> None:
    config = load_config("sim")
    monitor_params = config.system_monitor.model_copy(
        update={"period_s": 0.05, "probe_timeout_s": 0.1, "max_age_s": 1.0}
    )
    config = config.model_copy(update={"system_monitor": monitor_params})
    probe = ControlledProbe()
    monitor = SystemMonitor(config, probe=probe)
    ctx = _Ctx()

    async def scenario() -> None:
        service = asyncio.ensure_future(monitor.run(ctx))  # type: ignore[arg-type]
        ticks = 0
        try:
            for _ in range(40):  # 0.4 s with the probe stuck
                await asyncio.sleep(0.01)
                ticks += 1
            assert ticks == 40
            assert probe.calls == 1  # no second probe beside the stuck one
            assert monitor.problem.startswith("probe stuck")
            assert ctx.beats >= 2  # the service itself is alive
            assert monitor.topic.latest() is None
            probe.release.set()
            for _ in range(100):
                await asyncio.sleep(0.01)
                if monitor.topic.latest() is not None:
                    break
            assert monitor.topic.latest() is not None
            assert monitor.problem == ""
            probe.fail = True
            seen = monitor.topic.latest()
            for _ in range(100):
                await asyncio.sleep(0.01)
                if monitor.problem:
                    break
            assert monitor.problem.startswith("probe failed")
            assert monitor.topic.latest() is seen  # a failed probe publishes nothing
        finally:
            probe.release.set()
            service.cancel()
            await asyncio.gather(service, return_exceptions=True)

    asyncio.run(scenario())
