"""The control loop service: a fixed-rate, heart-beating shell around a pure control core.

Each cycle the loop asks the core for commands at an explicit time and hands them to the
command sinks. Until the mode machine exists the only core is :class:`HoldSafeCore`,
which holds every actuator in the safe state: nothing can be engaged yet, so the only
honest output is "throttle 0, brake on, steering released". The loop's heartbeat is what
lets the daemon pet systemd's watchdog.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from appliance.logs import get_logger
from appliance.supervisor import ServiceContext
from appliance.timing import FixedRateTicker
from safety.safe_stop import SafeCommand

log = get_logger("control")


@dataclass(frozen=True)
class CycleOutput:
    now_s: float
    command: SafeCommand
    engaged: bool


class ControlCore(Protocol):
    def step(self, now_s: float) -> CycleOutput: ...


class HoldSafeCore:
    """The core before any engagement is possible: always the safe command."""

    def __init__(self, safe_command: SafeCommand) -> None:
        self._safe_command = safe_command

    def step(self, now_s: float) -> CycleOutput:
        return CycleOutput(now_s=now_s, command=self._safe_command, engaged=False)


CommandSink = Callable[[CycleOutput], None]


class ControlLoop:
    """Runs ``core.step`` at ``rate_hz``; a supervised, critical service."""

    def __init__(
        self,
        core: ControlCore,
        rate_hz: float,
        sinks: list[CommandSink] | None = None,
    ) -> None:
        self.core = core
        self.ticker = FixedRateTicker(1.0 / rate_hz)
        self.sinks = list(sinks or [])
        self.last_output: CycleOutput | None = None

    async def run(self, ctx: ServiceContext) -> None:
        self.ticker.reset()
        log.info("control_loop_started", rate_hz=round(1.0 / self.ticker.period_s, 3))
        while True:
            now_s = await self.ticker.tick()
            output = self.core.step(now_s)
            for sink in self.sinks:
                sink(output)
            self.last_output = output
            ctx.beat()
