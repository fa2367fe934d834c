"""The control loop on the built-in simulated vehicle: timing, and how fast it lets go.

The daemon runs on the ``sim`` profile in this process (both scanners streaming from their
twins, the boards on ptys, the PC104 twin on python-can's ``virtual`` bus), with the
~4,000 frames/s load generator of bench_pc104 on the same virtual bus, at two control
rates (``rates.control_hz`` and ``rates.pc104_command_hz`` together). Figures:

1. control loop wake-up jitter and missed cycles, and the core's step time, engaged;
2. a stale input to the safe command on the wire: the steering twin stops its telemetry;
   from the moment the input is stale (its last frame's receive stamp plus
   ``staleness.steering_pot_max_age_s``) to the brake twin receiving
   ``BrakeCommand(enable=True)`` and a STOP HL_MotionCommand on the bus. Target p99: one
   cycle + 5 ms;
3. the operator taking over: from the daemon receiving the telemetry frame with the
   panel's new MANUAL_OVERRIDE count to the steering twin receiving RELEASE and a STOP
   on the bus; from the daemon receiving the brake frame of a tap in speed hold to a
   set-point that left the hold on the bus. Target p99:
   one cycle.

Where the twins receive: the boards read their pty the moment bytes arrive (an
``add_reader`` on the twin's end runs its ``step``), not at their own 10 ms step, so the
figure is the daemon's; HL_MotionCommand frames are stamped by a second node on the bus
(a thread blocked in ``recv``), not by the PC104 twin, which reads on its own 5 ms tick.
"core" is the control cycle whose output first shows the change (its wake-up time): the
rest is the driver and the link.
Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import platform
import random
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

from appliance.config import VehicleConfig, load_config
from appliance.config.models import SimPlacement
from appliance.control_loop import StepTimes
from appliance.core.core import CoreOutput
from appliance.daemon import Daemon
from appliance.modes import AUTOMATIC_MODES, Mode
from benchmarks.bench_pc104 import LoadGenerator
from benchmarks.stats import summarize
from drivers.actuators.messages import BUTTON_ORDER, Buttons, SteeringMode
from drivers.actuators.twin import BoardTwin
from drivers.pc104 import protocol
from drivers.pc104.messages import MotionCommand, MotionPattern
from drivers.topics import Topic

RATES_HZ = (50.0, 100.0)
TRIALS = 30
# A loaded 500 kbit/s bus (about a quarter of its capacity). The virtual bus lives in
# this process, so every filler frame is Python work under the daemon's GIL: 4,000
# frames/s (what earlier runs offered) kept a 2-core VM's loop 95 % busy on its own.
BUS_LOAD_FPS = 1000
WAIT_S = 5.0  # for any one step of a trial: the daemon answers in milliseconds
TAP_PCT, TAP_S = 40.0, 0.15
OVERRIDE_INDEX = BUTTON_ORDER.index(Buttons.MANUAL_OVERRIDE)


class CommandLog:
    """Each change of the command a twin follows, with the time it received it."""

    def __init__(self) -> None:
        self.changes: list[tuple[float, Any]] = []

    def note(self, now_s: float, command: Any) -> None:
        if command is not None and (not self.changes or self.changes[-1][1] != command):
            self.changes.append((now_s, command))

    def first_after(self, t0_s: float, test: Callable[[Any], bool]) -> float | None:
        return next((t for t, c in self.changes if t >= t0_s and test(c)), None)


def read_on_arrival(twin: BoardTwin[Any], log: CommandLog) -> Callable[[], None]:
    """Step the board the moment the daemon's bytes reach its pty; returns the undo."""
    fd = twin.link._master  # the twin's end of the pty (no public handle)
    assert fd is not None
    loop = asyncio.get_running_loop()

    def on_readable() -> None:
        now_s = time.monotonic()
        twin.step(now_s)
        log.note(now_s, twin.command)

    def undo() -> None:
        loop.remove_reader(fd)

    loop.add_reader(fd, on_readable)
    return undo


class WireListener:
    """A second node on the bus: logs each HL_MotionCommand the moment it is on the wire.

    The PC104 twin reads the bus on its own 5 ms tick, which would be in every figure; a
    listener thread blocked in ``recv`` stamps the frame as it arrives instead.
    """

    def __init__(self, channel: str, log: CommandLog) -> None:
        self._bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self._log = log
        self._stop = threading.Event()
        self._command_id = protocol.spec_for(MotionCommand).frame_id
        self._thread = threading.Thread(target=self._run, name="wire-listener", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            message = self._bus.recv(0.05)
            if message is None or message.arbitration_id != self._command_id:
                continue
            now_s = time.monotonic()
            with contextlib.suppress(protocol.Pc104ProtocolError):
                frame = protocol.decode(message.arbitration_id, bytes(message.data), now_s)
                self._log.note(now_s, frame.message)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._bus.shutdown()


class FirstSample:
    """The receive stamp of the first sample published on a topic that passes a test."""

    def __init__(self, topic: Topic[Any]) -> None:
        self._publish = topic.publish
        topic.publish = self._published  # type: ignore[method-assign]
        self._test: Callable[[Any], bool] | None = None
        self.stamp_s: float | None = None

    def arm(self, test: Callable[[Any], bool]) -> None:
        self._test, self.stamp_s = test, None

    def _published(self, value: Any, stamp_s: float) -> Any:
        sample = self._publish(value, stamp_s)
        if self._test is not None and self.stamp_s is None and self._test(value):
            self.stamp_s = stamp_s
        return sample


def changed_to(output: CoreOutput, mode: Mode, cause: str) -> bool:
    """Whether this cycle changed the mode to ``mode`` because of ``cause`` (an event)."""
    return any(
        n.event == "mode_changed" and n.fields["to_mode"] == mode and n.fields["cause"] == cause
        for n in output.notes
    )


def raised(output: CoreOutput, fault: str) -> bool:
    return any(n.event == "fault_raised" and n.fields["fault"] == fault for n in output.notes)


class FirstOutput:
    """The wake-up time of the first control cycle whose output passes a test; and
    every fault raised, so a window can say whether the process stalled in it."""

    def __init__(self) -> None:
        self._test: Callable[[CoreOutput], bool] | None = None
        self.now_s: float | None = None
        self.faults_raised: list[str] = []

    def arm(self, test: Callable[[CoreOutput], bool]) -> None:
        self._test, self.now_s = test, None

    def __call__(self, output: CoreOutput) -> None:
        if self._test is not None and self.now_s is None and self._test(output):
            self.now_s = output.now_s
        self.faults_raised += [n.fields["fault"] for n in output.notes if n.event == "fault_raised"]


@dataclass
class Latencies:
    """Milliseconds per measured path; None where a trial saw nothing (reported)."""

    paths: dict[str, list[float | None]] = field(default_factory=dict)
    spoiled: int = 0  # trials another fault got to first (a stalled process), repeated

    @property
    def trials(self) -> int:
        return max((len(v) for v in self.paths.values()), default=0)

    def add(self, path: str, start_s: float, end_s: float | None) -> None:
        value = None if end_s is None else (end_s - start_s) * 1e3
        self.paths.setdefault(path, []).append(value)

    def lines(self, title: str, target_ms: float) -> list[str]:
        spoiled = f", {self.spoiled} more spoiled by another fault" if self.spoiled else ""
        out = [f"  {title} ({self.trials} trials{spoiled}; target p99 <= {target_ms:.1f} ms):"]
        for path, values in self.paths.items():
            seen = [v for v in values if v is not None]
            missing = len(values) - len(seen)
            line = "    " + summarize(path, seen, "ms")
            out.append(line + (f", {missing} trial(s) saw nothing" if missing else ""))
        return out


class Bench:
    def __init__(self, config: VehicleConfig, socket_path: str) -> None:
        self.daemon = Daemon(config, control_socket=socket_path)
        self.config = config
        sim = self.daemon.io.simulator
        assert sim is not None and sim.board_twins is not None and sim.pc104_twin is not None
        self.twins = sim.board_twins
        self.pc104_twin = sim.pc104_twin
        self.core = self.daemon.core
        self.period_s = 1.0 / config.rates.control_hz
        self.logs = {name: CommandLog() for name in ("steering", "brake", "pc104")}
        self.first_output = FirstOutput()
        self.daemon.control.on_output.append(self.first_output)
        topics = self.daemon.io.topics
        self.panel_sample = FirstSample(topics.get("board.panel"))
        self.brake_sample = FirstSample(topics.get("board.brake"))
        self.rng = random.Random(7)

    async def until(
        self, what: str, condition: Callable[[], bool], timeout_s: float = WAIT_S
    ) -> None:
        deadline_s = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline_s:
                state = self.core.state
                raise RuntimeError(
                    f"no {what} within {timeout_s} s: mode {state.mode}, "
                    f"faults {[f.reason for f in state.faults]}, "
                    f"active {sorted(self.core.faults.active_faults)}, "
                    f"refusal {self.core.last_refusal}"
                )
            await asyncio.sleep(0.002)

    def request(self, name: str) -> None:
        self.core.request(name, time.monotonic())

    async def to_mode(self, mode: Mode) -> None:
        """Bring the core to READY or ENGAGED the way a bench operator would."""
        deadline_s = time.monotonic() + WAIT_S
        while (now := self.core.state.mode) is not mode:
            faulted = bool(self.core.state.faults or self.core.faults.active_faults)
            if now in AUTOMATIC_MODES or (now is Mode.ERROR and not faulted):
                self.request("disengage")
            elif now is Mode.READY and mode is Mode.ENGAGED:
                self.request("engage")
            if time.monotonic() > deadline_s:
                await self.until(str(mode), lambda: False)  # raises, with the state
            await asyncio.sleep(self.period_s)

    async def jitter(self, seconds: float) -> list[str]:
        await self.to_mode(Mode.ENGAGED)
        control = self.daemon.control
        control.ticker.stats.reset()
        control.step_times = StepTimes()
        self.first_output.faults_raised.clear()
        cpu0_s, wall0_s = time.process_time(), time.monotonic()
        await asyncio.sleep(seconds)
        cpu_pct = 100 * (time.process_time() - cpu0_s) / (time.monotonic() - wall0_s)
        r = control.ticker.stats.report()
        scans = ", ".join(f"{s.health.scans_per_s:.1f}" for s in self.daemon.io.scanners.values())
        faults = self.first_output.faults_raised
        return [
            f"  loop ({seconds:g} s, from ENGAGED): {r.cycles} cycles, "
            f"{r.overruns} missed; wake-up jitter p50 {r.jitter_p50_ms:.3f} ms, "
            f"p99 {r.jitter_p99_ms:.3f} ms, max {r.jitter_max_ms:.3f} ms",
            f"  core step p99 {control.step_times.p99_ms():.3f} ms; process CPU {cpu_pct:.0f} % "
            f"of one core; scans/s left, right: {scans}",
            f"  faults raised in the window: {len(faults)}"
            + (f" ({', '.join(sorted(set(faults)))})" if faults else ""),
        ]

    async def stale_input(self, trials: int) -> Latencies:
        out = Latencies()
        while out.trials < trials and out.spoiled < trials:
            await self.to_mode(Mode.ENGAGED)
            await asyncio.sleep(self.rng.uniform(0.05, 0.05 + self.period_s))
            await self.stale_trial(out)
            await self.to_mode(Mode.READY)
        return out

    async def stale_trial(self, out: Latencies) -> None:
        brake_log, pc104_log = self.logs["brake"], self.logs["pc104"]
        # The cycle that faults because of this stall: ENGAGED -> ERROR, the pot stale.
        self.first_output.arm(
            lambda o: changed_to(o, Mode.ERROR, "FaultRaised") and raised(o, "stale:steering.pot")
        )
        t0_s = time.monotonic()
        self.twins.steering.stall(True)

        def safe_received() -> bool:
            brake = brake_log.first_after(t0_s, _is_enable)
            return brake is not None and pc104_log.first_after(t0_s, _is_stop) is not None

        with contextlib.suppress(RuntimeError):
            await self.until("safe commands", safe_received)
        # The last frame the daemon received before the stall (none is in flight by now).
        sample = self.daemon.io.topics.get("board.steering").latest()
        assert sample is not None
        stale_s = sample.stamp_s + self.config.staleness.steering_pot_max_age_s
        self.twins.steering.stall(False)
        if self.first_output.now_s is None:  # another fault was first: not this figure
            out.spoiled += 1
            return
        out.add("stale -> core cycle commands safe", stale_s, self.first_output.now_s)
        out.add(
            "stale -> brake twin has BrakeCommand(enable=True)",
            stale_s,
            brake_log.first_after(t0_s, _is_enable),
        )
        out.add("stale -> STOP on the bus", stale_s, pc104_log.first_after(t0_s, _is_stop))

    async def operator(self, trials: int) -> tuple[Latencies, Latencies]:
        override, tap = Latencies(), Latencies()
        while min(override.trials, tap.trials) < trials and override.spoiled + tap.spoiled < trials:
            held_mps = await self.speed_hold()
            if tap.trials < trials:
                await self.tap_trial(tap, held_mps)
            await self.to_mode(Mode.ENGAGED)  # after the tap (or the fault that spoiled it)
            await self.until("the pedals released", self._pedals_released)
            await asyncio.sleep(self.rng.uniform(0.0, self.period_s))
            if override.trials < trials:
                await self.override_trial(override)
            await self.to_mode(Mode.READY)
        return override, tap

    async def speed_hold(self) -> float:
        """SPEED_HOLD one step above standstill, that set speed at the PC104; returns it."""
        deadline_s = time.monotonic() + WAIT_S
        while self.core.state.mode is not Mode.SPEED_HOLD:
            await self.to_mode(Mode.ENGAGED)
            self.request("speed_plus")  # the hold starts at the measured speed: at rest
            if time.monotonic() > deadline_s:
                await self.until("speed hold", lambda: False)  # raises, with the state
            await asyncio.sleep(self.period_s)
        self.request("speed_plus")  # one step up
        held = self.core.state.set_speed_mps
        assert held is not None and held > 0.0, self.core.state
        pc104_log = self.logs["pc104"]

        def at_pc104() -> bool:
            latest = pc104_log.changes[-1][1] if pc104_log.changes else None
            return latest is not None and abs(latest.speed_mps - held) < 1e-3

        await self.until("the set speed at the PC104", at_pc104)
        await asyncio.sleep(self.rng.uniform(0.0, self.period_s))
        return held

    async def tap_trial(self, out: Latencies, held_mps: float) -> None:
        margin = self.config.safety.pedal_override_margin_pct
        pc104_log = self.logs["pc104"]
        self.brake_sample.arm(lambda v: v.pedal_position_pct > v.actuator_position_pct + margin)
        self.first_output.arm(lambda o: changed_to(o, Mode.ENGAGED, "BrakeTap"))
        t0_s = time.monotonic()
        self.twins.brake.operator_brake_tap(TAP_PCT, TAP_S)

        def left_hold() -> float | None:
            return pc104_log.first_after(t0_s, lambda c: abs(c.speed_mps - held_mps) > 1e-3)

        with contextlib.suppress(RuntimeError):
            await self.until("the hold left", lambda: left_hold() is not None)
        pressed_s = self.brake_sample.stamp_s
        if pressed_s is None or self.first_output.now_s is None:
            out.spoiled += 1
        else:
            out.add("brake frame -> core cycle leaves the hold", pressed_s, self.first_output.now_s)
            out.add("brake frame -> set-point left the hold on the bus", pressed_s, left_hold())

    async def override_trial(self, out: Latencies) -> None:
        steering_log, pc104_log = self.logs["steering"], self.logs["pc104"]
        count = (self.twins.panel.press_counts[OVERRIDE_INDEX] + 1) & 0xFF
        self.panel_sample.arm(lambda v: v.press_count(Buttons.MANUAL_OVERRIDE) == count)
        self.first_output.arm(lambda o: changed_to(o, Mode.READY, "ManualOverridePressed"))
        t0_s = time.monotonic()
        self.twins.panel.press(Buttons.MANUAL_OVERRIDE)

        def handed_back() -> bool:
            steering = steering_log.first_after(t0_s, _is_release)
            return steering is not None and pc104_log.first_after(t0_s, _is_stop) is not None

        with contextlib.suppress(RuntimeError):
            await self.until("control handed back", handed_back)
        pressed_s = self.panel_sample.stamp_s
        if pressed_s is None or self.first_output.now_s is None:
            out.spoiled += 1
        else:
            out.add("panel frame -> core cycle READY", pressed_s, self.first_output.now_s)
            out.add(
                "panel frame -> steering twin has RELEASE",
                pressed_s,
                steering_log.first_after(t0_s, _is_release),
            )
            out.add(
                "panel frame -> STOP on the bus",
                pressed_s,
                pc104_log.first_after(t0_s, _is_stop),
            )

    def _pedals_released(self) -> bool:
        output = self.core.last_output
        return output is not None and not output.operator.overriding


def _is_enable(command: Any) -> bool:
    return bool(command.enable)


def _is_stop(command: Any) -> bool:
    return bool(command.pattern is MotionPattern.STOP)


def _is_release(command: Any) -> bool:
    return bool(command.mode is SteeringMode.RELEASE)


def bench_config(rate_hz: float, channel: str) -> VehicleConfig:
    """The sim profile with its twins inline: they are this benchmark's instruments (it
    stalls a board, taps a pedal, stamps what each twin receives), so they share the
    daemon's loop here, unlike `dbw run --config sim` (bench_soak measures that)."""
    config = load_config("sim")
    rates = config.rates.model_copy(update={"control_hz": rate_hz, "pc104_command_hz": rate_hz})
    can = config.devices.can.model_copy(update={"channel": channel})
    devices = config.devices.model_copy(update={"can": can})
    simulation = config.simulation.model_copy(update={"placement": SimPlacement.INLINE})
    # Twins in the loop: the pot allowance the sim profile had while they were always there.
    staleness = config.staleness.model_copy(update={"steering_pot_max_age_s": 0.08})
    return config.model_copy(
        update={
            "rates": rates,
            "devices": devices,
            "simulation": simulation,
            "staleness": staleness,
        }
    )


async def bench_rate(
    rate_hz: float, seconds: float, trials: int, bus_load_fps: int = BUS_LOAD_FPS
) -> list[str]:
    channel = f"bench-control-{uuid.uuid4().hex[:8]}"
    period_ms = 1e3 / rate_hz
    with tempfile.TemporaryDirectory(prefix="dbw-bench-") as directory:
        bench = Bench(bench_config(rate_hz, channel), os.path.join(directory, "control.sock"))
        run = asyncio.ensure_future(bench.daemon.run(handle_signals=False))
        undo: list[Callable[[], None]] = []
        try:
            await bench.until("READY", lambda: bench.core.state.mode is Mode.READY, 60.0)
            # Filler ids only. In this process, beside every twin: each frame is Python
            # work for the generator and every receiving node, all under one GIL.
            generator = LoadGenerator(channel, with_status=False, total_fps=bus_load_fps)
            generator.start()
            undo.append(lambda: _stop(generator))
            wire = WireListener(channel, bench.logs["pc104"])
            undo.append(wire.close)
            lines = [f"### control at {rate_hz:g} Hz (period {period_ms:.1f} ms)"]
            lines += await bench.jitter(seconds)
            sent0_s, sent0 = time.monotonic(), generator.sent
            for name in ("steering", "brake"):
                undo.append(read_on_arrival(bench.twins.boards[name], bench.logs[name]))
            stale = await bench.stale_input(trials)
            override, tap = await bench.operator(trials)
            offered = (generator.sent - sent0) / (time.monotonic() - sent0_s)
            lines += stale.lines("steering telemetry stops, ENGAGED", period_ms + 5.0)
            lines += override.lines("manual override press, ENGAGED", period_ms)
            lines += tap.lines("brake tap, SPEED_HOLD", period_ms)
            lines.append(f"  load generator: {offered:.0f} frames/s offered on the virtual bus")
            return lines
        finally:
            for step in reversed(undo):
                step()
            bench.daemon.request_stop("benchmark over")
            await asyncio.wait_for(run, 10.0)


def _stop(generator: LoadGenerator) -> None:
    generator.stop_event.set()
    generator.join(5.0)


def machine_header() -> list[str]:
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    return [
        "## control loop (benchmarks/bench_control.py)",
        f"machine: {platform.platform()}, Python {platform.python_version()}, "
        f"os.cpu_count() = {os.cpu_count()}, load average (1, 5, 15 min) = {load}",
        "note: on a shared 2-core VM these figures are noisy (other work, GIL contention "
        "with the load generator thread); compare runs on one machine, never assert them",
        "paths to the PC104 end when the frame is on the bus (a listener node stamps it); "
        "the boards' twins read their pty on arrival",
    ]


def main(argv: list[str] | None = None) -> None:
    from appliance.logs import configure_logging

    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_control")
    parser.add_argument("--seconds", type=float, default=20.0, help="jitter window per rate")
    parser.add_argument("--trials", type=int, default=TRIALS, help="repetitions per latency")
    parser.add_argument(
        "--bus-load-fps",
        type=int,
        default=BUS_LOAD_FPS,
        help=f"filler frames/s on the virtual CAN bus (default {BUS_LOAD_FPS})",
    )
    parser.add_argument(
        "--log-file", help="the daemon's log (JSON, info and up) goes here; default: none"
    )
    args = parser.parse_args([] if argv is None else argv)  # benchmarks.run passes none
    if args.log_file:
        configure_logging("info", stream=open(args.log_file, "w"), json=True)  # noqa: SIM115
    else:
        configure_logging("critical", stream=open(os.devnull, "w"), json=True)  # noqa: SIM115
    for line in machine_header():
        print(line)
    for rate_hz in RATES_HZ:
        for line in asyncio.run(bench_rate(rate_hz, args.seconds, args.trials, args.bus_load_fps)):
            print(line)


if __name__ == "__main__":
    main(sys.argv[1:])
