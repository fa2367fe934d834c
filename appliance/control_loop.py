"""The control loop service: a fixed-rate, heart-beating shell around the pure control core.

Each cycle takes the latest value of every input topic with its age, calls
``ControlCore.step(inputs, now_s)``, and hands the result to the command sinks (the
actuator boards and the PC104). The loop's heartbeat is what lets the daemon pet
systemd's watchdog, so a loop that hangs gets the process restarted; a loop that crashes
is restarted by the supervisor with a *new* core state (BOOT): nothing re-engages by
itself. Commands to the boards are leased for a few cycles, so a hung loop cannot keep
the vehicle steering on its last set-point (the PC104 client applies the same rule with
its command timeout).

Cycle timing (wake-up jitter, missed cycles) and the core's own step time are measured
and reported in the ``heartbeats`` log and in ``dbw status``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, Protocol

from appliance.core.core import ControlCore, CoreOutput
from appliance.core.inputs import TABLET_HOLD_TOPIC, ControlInputs, LinkCounts
from appliance.gnss_input import GNSS_POSE_TOPIC
from appliance.logs import get_logger
from appliance.supervisor import ServiceContext
from appliance.system_monitor import SYSTEM_HEALTH_TOPIC
from appliance.timing import FixedRateTicker, SampleWindow
from appliance.topics import TopicRegistry
from drivers.topics import Sample

log = get_logger("control")

# A command outlives its cycle by this many periods, then the boards stop hearing it.
LEASE_PERIODS = 3
# A cycle this many periods late (or a step this long) is a stall, logged every time.
STALL_PERIODS = 5


class CommandSink(Protocol):
    def send(self, output: CoreOutput) -> None: ...


class InputSource(Protocol):
    def read(self, now_s: float) -> ControlInputs: ...


class TopicInputs:
    """Builds the core's inputs from the daemon's topics (and the PC104 link's counters)."""

    def __init__(
        self,
        topics: TopicRegistry,
        link_counts: Callable[[], LinkCounts] | None = None,
        service_faults: Callable[[], dict[str, str]] | None = None,
        jobs_done: Callable[[], tuple[float, ...]] | None = None,
    ) -> None:
        self.topics = topics
        self.link_counts = link_counts
        self.service_faults = service_faults
        self.jobs_done = jobs_done

    def _latest(self, name: str) -> Any:
        sample = self.topics.get(name).latest()
        return None if sample is None else sample.value

    def read(self, now_s: float) -> ControlInputs:
        ages = self.topics.ages_s(now_s)
        # The steering pot travels in the steering board's telemetry; it has its own limit.
        ages["steering.pot"] = ages.get("board.steering", float("inf"))
        panel = self.topics.get("board.panel").latest()
        # Only a vehicle with a receiver has the topic; asking for it would register one.
        gnss = self.topics.get(GNSS_POSE_TOPIC).latest() if GNSS_POSE_TOPIC in ages else None
        return ControlInputs(
            ages_s=ages,
            steering=self._latest("board.steering"),
            throttle=self._latest("board.throttle"),
            brake=self._latest("board.brake"),
            panel=None if panel is None else panel.value,
            panel_seq=None if panel is None else panel.seq,
            pc104_status=self._latest("pc104.status"),
            pc104_link=self.link_counts() if self.link_counts is not None else LinkCounts(),
            scans={side: self._latest(f"scan.{side}") for side in ("left", "right")},
            service_faults=self.service_faults() if self.service_faults is not None else {},
            gnss=None if gnss is None else gnss.value,
            gnss_seq=None if gnss is None else gnss.seq,
            system=self._latest(SYSTEM_HEALTH_TOPIC) if SYSTEM_HEALTH_TOPIC in ages else None,
            # Only a daemon serving the tablet page has the topic (see GNSS above).
            tablet=self._latest(TABLET_HOLD_TOPIC) if TABLET_HOLD_TOPIC in ages else None,
            jobs_done=self.jobs_done() if self.jobs_done is not None else (),
        )


class OperatorWatch:
    """Wakes the control loop at once when telemetry shows the operator acting.

    The loop runs on a fixed schedule, so a button pressed just after a cycle would wait
    up to a whole period; the operator's override must win within one cycle, so a panel
    frame with a new press or a changed button (the e-stop mushroom among them) and a
    pedal newly pressed past our actuator run an extra cycle now. The schedule is kept.
    Only changes wake it, so a held button or a resting foot costs nothing.
    """

    def __init__(self, wake: Callable[[], None], pedal_margin_pct: float) -> None:
        self._wake = wake
        self._margin_pct = pedal_margin_pct
        self._panel: tuple[object, ...] | None = None
        self._pressed: dict[str, bool] = {}

    def on_panel(self, sample: Sample[Any]) -> None:
        value = sample.value
        seen = (tuple(value.press_counts), value.buttons_down)
        if self._panel is not None and seen != self._panel:
            self._wake()
        self._panel = seen

    def on_pedal(self, name: str) -> Callable[[Sample[Any]], None]:
        def listener(sample: Sample[Any]) -> None:
            pedal = sample.value.pedal_position_pct
            pressed = pedal is not None and (
                pedal > sample.value.actuator_position_pct + self._margin_pct
            )
            if pressed and not self._pressed.get(name, False):
                self._wake()
            self._pressed[name] = pressed

        return listener


class StepTimes:
    """The core's compute time per cycle, over a bounded window."""

    def __init__(self, window: int = 5000) -> None:
        self._s = SampleWindow(window)

    def update(self, seconds: float) -> None:
        self._s.append(seconds)

    def p99_ms(self) -> float:
        return self._s.percentiles([99])[0] * 1e3


class SlowCycleLog:
    """Logs a late wake-up or a step longer than the period, at most once per second.

    A stall shows afterwards only as stale inputs, and those blame the devices; this
    line says the loop itself was late or slow, by how much, and how often since the last
    line, so an incident can be told from a device that stopped talking. A stall of
    ``STALL_PERIODS`` or more is always logged: it is the one an incident needs.
    """

    def __init__(self, min_interval_s: float = 1.0) -> None:
        self.min_interval_s = min_interval_s
        self._last_s = -math.inf
        self._suppressed = 0

    def reset(self) -> None:
        self._last_s = -math.inf
        self._suppressed = 0

    def update(self, now_s: float, late_ms: float, step_ms: float, period_ms: float) -> None:
        if late_ms < period_ms and step_ms < period_ms:
            return
        stall = max(late_ms, step_ms) >= STALL_PERIODS * period_ms
        if now_s - self._last_s < self.min_interval_s and not stall:
            self._suppressed += 1
            return
        log.warning(
            "control_cycle_slow",
            late_ms=round(late_ms, 1),
            step_ms=round(step_ms, 1),
            period_ms=round(period_ms, 1),
            earlier_unlogged=self._suppressed,
        )
        self._last_s = now_s
        self._suppressed = 0


class ControlLoop:
    """Runs ``core.step`` at ``rate_hz``; a supervised, critical service."""

    def __init__(
        self,
        core: ControlCore,
        inputs: InputSource,
        rate_hz: float,
        sinks: list[CommandSink] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.core = core
        self.inputs = inputs
        self.rate_hz = rate_hz
        self.ticker = FixedRateTicker(1.0 / rate_hz, clock=clock)
        self.sinks = list(sinks or [])
        self.last_output: CoreOutput | None = None
        self.step_times = StepTimes()
        self._clock = clock
        self.on_output: list[Callable[[CoreOutput], None]] = []
        # Called with each cycle's time, the inputs the core saw and its output (the
        # recorder), and with the time of each (re)start of the core: replay needs both.
        self.on_cycle: list[Callable[[float, ControlInputs, CoreOutput], None]] = []
        self.on_start: list[Callable[[float], None]] = []
        self.halted = False
        self.slow_cycles = SlowCycleLog()

    @property
    def lease_s(self) -> float:
        return LEASE_PERIODS * self.ticker.period_s

    def halt(self) -> None:
        """Stop sending: the daemon is shutting down and has commanded the safe state
        itself; a cycle after that must not overwrite it."""
        self.halted = True

    def cycle(self, now_s: float) -> CoreOutput:
        """One cycle; public so tests and benchmarks can drive the loop with a fake clock."""
        started = self._clock()
        inputs = self.inputs.read(now_s)
        output = self.core.step(inputs, now_s)
        step_s = self._clock() - started
        self.step_times.update(step_s)
        period_ms = self.ticker.period_s * 1e3
        self.slow_cycles.update(now_s, self.ticker.last_late_s * 1e3, step_s * 1e3, period_ms)
        if not self.halted:
            for sink in self.sinks:
                sink.send(output)
        for note in output.notes:
            level = log.error if note.event == "fault_raised" else log.info
            level(note.event, mode=str(output.mode), **note.fields)
        for hook in self.on_output:
            hook(output)
        for cycle_hook in self.on_cycle:
            cycle_hook(now_s, inputs, output)
        self.last_output = output
        return output

    async def run(self, ctx: ServiceContext) -> None:
        # Every (re)start begins in BOOT: a restarted loop never resumes an engagement.
        self.core.reset()
        for start_hook in self.on_start:
            start_hook(self._clock())
        self.ticker.reset()
        self.slow_cycles.reset()
        log.info("control_loop_started", rate_hz=round(self.rate_hz, 3))
        while True:
            now_s = await self.ticker.tick()
            self.cycle(now_s)
            ctx.beat()

    def loop_figures(self) -> dict[str, float | int | str]:
        report = self.ticker.stats.report()
        return {
            "rate_hz": self.rate_hz,
            "cycles": report.cycles,
            "overruns": report.overruns,
            "jitter_p50_ms": round(report.jitter_p50_ms, 3),
            "jitter_p99_ms": round(report.jitter_p99_ms, 3),
            "jitter_max_ms": round(report.jitter_max_ms, 3),
            "step_p99_ms": round(self.step_times.p99_ms(), 3),
            "early_wakes": self.ticker.early_wakes,
            # How the loop wakes: "timerfd" (to the microsecond) or "asyncio timer" (to
            # the millisecond, rounded up: a system without timerfd, or a fake clock).
            "wakes_by": "timerfd" if self.ticker.precise else "asyncio timer",
        }
