"""The daemon's control behaviour against the simulated vehicle, in real time.

Every test runs the whole daemon on the built-in "sim" profile as shipped: the simulated
vehicle in its own process, reached over TCP, ptys and a simulated SLCAN adapter exactly
as hardware is, and the supervisor owning every task. Through the simulated vehicle's
bench socket (``tests.runtime.twin_view``) a test presses the panel's buttons, moves the
operator's hands and feet, and breaks links and devices, then checks what the twins were
told and when; it breaks the daemon's own services from inside. Liveness waits are
generous (the machine is shared); where the requirement is "within one control cycle"
the latency is measured and asserted against 0.1 s, and printed (``pytest -s``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import shutil
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click
import pytest
from click.testing import CliRunner, Result

from appliance.cli.control import engage as engage_command
from appliance.cli.control import status as status_command
from appliance.config import VehicleConfig, load_config
from appliance.control_client import query
from appliance.core.core import CoreOutput
from appliance.daemon import Daemon, RunResult
from appliance.modes import Mode
from appliance.supervisor import ServiceState
from drivers.actuators.messages import BrakeCommand, BrakeTelemetry, Lamps, SteeringMode
from drivers.pc104.messages import HighLevelState, MotionPattern
from tests.runtime.inline import isolated
from tests.runtime.twin_view import TwinView
from tools.fake_notify import FakeNotifySocket

pytestmark = pytest.mark.slow

READY_TIMEOUT_S = 30.0  # the simulated vehicle's process starts first (imports, site)
LIVENESS_TIMEOUT_S = 5.0  # things that must happen, eventually, on a loaded machine
REACTION_LIMIT_S = 0.1  # one control period plus telemetry delay, with room to spare
POLL_S = 0.01
LATENCY_POLL_S = 0.002  # finer, so a measured latency is not mostly polling
WATCHDOG_S = 0.4  # WatchdogSec= for the hang test: pings every 0.2 s


# ---------------------------------------------------------------- recording what happens


@dataclass
class ModeLog:
    """Every mode the control loop put out, as (cycle time, mode) at each change."""

    changes: list[tuple[float, Mode]] = field(default_factory=list)

    def on_output(self, output: CoreOutput) -> None:
        if not self.changes or self.changes[-1][1] is not output.mode:
            self.changes.append((output.now_s, output.mode))

    def since(self, start_s: float) -> list[Mode]:
        """The mode at ``start_s`` and every mode entered after it."""
        before = [mode for at_s, mode in self.changes if at_s <= start_s]
        after = [mode for at_s, mode in self.changes if at_s > start_s]
        return before[-1:] + after

    def entered_after(self, start_s: float) -> list[Mode]:
        return [mode for at_s, mode in self.changes if at_s > start_s]

    def entered_s(self, mode: Mode, after_s: float) -> float | None:
        return next((at_s for at_s, m in self.changes if m is mode and at_s > after_s), None)


class BrakePedalTap:
    """Every brake-board telemetry sample the daemon received, with its receive stamp."""

    def __init__(self, daemon: Daemon) -> None:
        self.samples: list[tuple[float, BrakeTelemetry]] = []
        self._topic = daemon.io.topics.get("board.brake")
        self._task = asyncio.ensure_future(self._record())

    async def _record(self) -> None:
        seq = 0
        while True:
            sample = await self._topic.wait_next(seq)
            seq = sample.seq
            self.samples.append((sample.stamp_s, sample.value))

    def first_pressed_s(self, after_s: float, margin_pct: float) -> float | None:
        for stamp_s, telemetry in self.samples:
            pedal_pct = telemetry.pedal_position_pct
            if pedal_pct is None:
                continue
            if stamp_s > after_s and pedal_pct > telemetry.actuator_position_pct + margin_pct:
                return stamp_s
        return None

    async def close(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task


# ---------------------------------------------------------------- the running daemon


@dataclass
class Sim:
    daemon: Daemon
    twins: TwinView  # the simulated vehicle, through its bench socket
    socket_path: str
    modes: ModeLog
    # False for a test that leaves a task stuck: the daemon then reports a forced exit.
    clean_exit_expected: bool = True
    result: RunResult | None = None

    @property
    def mode(self) -> Mode:
        return self.daemon.core.state.mode

    def status_text(self) -> str:
        doc = self.daemon.status_document()
        doc["fault_history"] = doc.get("fault_history", [])[-5:]
        doc["twins"] = self.twins.state
        doc["bench_errors"] = self.twins.poll_errors[-5:]
        return json.dumps(doc, indent=1, default=str)

    def fault_keys(self) -> set[str]:
        return {fault["key"] for fault in self.daemon.status_document()["faults"]}

    async def press(self, button: str) -> None:
        await self.twins.act("press", button=button)


def isolated_sim_config() -> VehicleConfig:
    """The sim profile as shipped, on free scanner ports (parallel runs).

    The PC104 link needs no isolation: it runs through a simulated SLCAN adapter on a
    pty in the simulated vehicle's own directory.
    """
    return isolated(load_config("sim"))


@contextlib.asynccontextmanager
async def running_sim() -> AsyncIterator[Sim]:
    """The daemon on "sim" in the background, READY; stopped (and checked) on the way out."""
    config = isolated_sim_config()
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")  # sun_path is 108 bytes
    socket_path = str(Path(directory) / "control.sock")
    daemon = Daemon(config, control_socket=socket_path)
    sim_process = daemon.io.sim_process
    assert sim_process is not None and daemon.io.simulator is None
    twins = TwinView(sim_process.bench_path)
    modes = ModeLog()
    daemon.control.on_output.append(modes.on_output)
    sim = Sim(daemon=daemon, twins=twins, socket_path=socket_path, modes=modes)
    run: asyncio.Future[RunResult] = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        await wait_until(sim, lambda: sim.mode is Mode.READY, READY_TIMEOUT_S, "mode READY")
        # READY is safe to hand over, not yet ready to engage: the PC104 reports its
        # command timeout until our commands have reached it.
        await wait_until_engageable(sim)
        await twins.start()
        yield sim
    finally:
        await twins.close()
        daemon.request_stop("test over")
        try:
            sim.result = await asyncio.wait_for(run, 5.0)
        finally:
            shutil.rmtree(directory, ignore_errors=True)
    if sim.clean_exit_expected:
        assert sim.result.exit_code == 0 and not sim.result.must_force_exit, sim.result


async def wait_until(
    sim: Sim,
    predicate: Callable[[], bool],
    timeout_s: float,
    what: str,
    poll_s: float = POLL_S,
) -> float:
    """Poll until ``predicate()``; return how long it took, or fail showing the status."""
    started_s = time.monotonic()
    while not predicate():
        if time.monotonic() - started_s > timeout_s:
            pytest.fail(f"{what}: not within {timeout_s} s; status:\n{sim.status_text()}")
        await asyncio.sleep(poll_s)
    return time.monotonic() - started_s


async def latencies(
    sim: Sim,
    started_s: float,
    probes: Mapping[str, Callable[[], bool]],
    timeout_s: float = LIVENESS_TIMEOUT_S,
) -> dict[str, float]:
    """Seconds from ``started_s`` until each probe was first seen true (fine polling).

    A probe of a twin reads the bench's latest observation, so its latency is known to
    ``twin_view.BENCH_POLL_S``.
    """
    seen: dict[str, float] = {}
    while len(seen) < len(probes):
        now_s = time.monotonic()
        for name, probe in probes.items():
            if name not in seen and probe():
                seen[name] = now_s - started_s
        if now_s - started_s > timeout_s:
            missing = sorted(set(probes) - set(seen))
            pytest.fail(f"{missing} not within {timeout_s} s; status:\n{sim.status_text()}")
        await asyncio.sleep(LATENCY_POLL_S)
    return seen


async def holds(sim: Sim, predicate: Callable[[], bool], duration_s: float, what: str) -> None:
    """Fail if ``predicate()`` is false at any poll during ``duration_s``."""
    end_s = time.monotonic() + duration_s
    while time.monotonic() < end_s:
        if not predicate():
            pytest.fail(
                f"{what}: broke after {duration_s - (end_s - time.monotonic()):.3f} s; "
                f"status:\n{sim.status_text()}"
            )
        await asyncio.sleep(POLL_S)


def report(test: str, figures: Mapping[str, float]) -> None:
    shown = ", ".join(f"{name} {seconds * 1e3:.1f} ms" for name, seconds in figures.items())
    print(f"[latency] {test}: {shown}")


async def wait_until_engageable(sim: Sim) -> None:
    await wait_until(
        sim, lambda: not sim.daemon.core.engage_blockers(), LIVENESS_TIMEOUT_S, "engageable"
    )


async def engage(sim: Sim) -> None:
    """Press engage once nothing blocks it, and wait until both steering paths are
    automatic."""
    twins = sim.twins
    await wait_until_engageable(sim)
    await sim.press("engage")
    await wait_until(sim, lambda: sim.mode is Mode.ENGAGED, LIVENESS_TIMEOUT_S, "ENGAGED")
    await wait_until(
        sim,
        lambda: twins.steering_mode() is SteeringMode.POSITION and twins.pc104_moving(),
        LIVENESS_TIMEOUT_S,
        "steering POSITION and a PC104 motion pattern",
    )


async def recover_to_ready(sim: Sim) -> None:
    """Wait for every fault to clear (the mode stays latched), then press OVERRIDE."""
    await wait_until(
        sim, lambda: not sim.daemon.status_document()["faults"], LIVENESS_TIMEOUT_S, "faults clear"
    )
    await holds(sim, lambda: sim.mode is Mode.ERROR, 0.3, "ERROR stays latched")
    cleared_s = time.monotonic()
    await sim.press("manual_override")
    await wait_until(sim, lambda: sim.mode is Mode.READY, LIVENESS_TIMEOUT_S, "READY")
    assert Mode.ENGAGED not in sim.modes.entered_after(cleared_s)


# ---------------------------------------------------------------- the tests


async def test_engage_from_the_panel_commands_every_path() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        # READY: nothing automatic yet (so the checks below can tell the difference).
        await wait_until(sim, lambda: twins.hl_state() is HighLevelState.STANDBY, 2.0, "HL STANDBY")
        await twins.refresh()
        assert twins.steering_mode() is not SteeringMode.POSITION
        assert not twins.pc104_moving()
        assert not twins.lamps() & Lamps.ENGAGED

        pressed_s = time.monotonic()
        await sim.press("engage")
        figures = await latencies(
            sim,
            pressed_s,
            {
                "ENGAGED": lambda: sim.mode is Mode.ENGAGED,
                "steering POSITION": lambda: twins.steering_mode() is SteeringMode.POSITION,
                "PC104 motion pattern": twins.pc104_moving,
                "panel lamp ENGAGED": lambda: bool(twins.lamps() & Lamps.ENGAGED),
                "HL heartbeat ENGAGED": lambda: twins.hl_state() is HighLevelState.ENGAGED,
            },
        )
        report("engage", figures)
        await wait_until(sim, lambda: twins.display_text() == "ENGAGED", 1.0, "panel text")
        assert twins.pc104_pattern() is MotionPattern.COUNTER_STEER  # the sim's default pattern
        assert not twins.lamps() & (Lamps.WARNING | Lamps.OVERRIDE)
        await holds(sim, lambda: sim.mode is Mode.ENGAGED, 0.5, "ENGAGED")


async def test_speed_hold_holds_the_speed_and_a_brake_tap_cancels_it() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        await twins.act("pedal", pedal="throttle", pct=40.0)
        await wait_until(sim, lambda: twins.speed_mps() > 0.3, 10.0, "vehicle moving")
        speed_at_press = (await twins.refresh())["world"]["speed_mps"]
        await sim.press("speed_plus")
        await wait_until(sim, lambda: sim.mode is Mode.SPEED_HOLD, 1.0, "SPEED_HOLD")
        set_speed = sim.daemon.core.state.set_speed_mps
        assert set_speed is not None
        assert set_speed == pytest.approx(speed_at_press, abs=0.1)
        await twins.act("pedal", pedal="throttle", pct=0.0)

        def holding() -> bool:
            in_band = abs(twins.speed_mps() - set_speed) <= 0.3
            return in_band and sim.mode is Mode.SPEED_HOLD

        await holds(sim, holding, 2.0, f"speed held at {set_speed:.2f} m/s +- 0.3")
        print(f"[speed] set {set_speed:.3f} m/s, after 2 s {twins.speed_mps():.3f} m/s")

        tap = BrakePedalTap(sim.daemon)
        try:
            tapped_s = time.monotonic()
            await twins.act("brake_tap", pct=30.0, duration_s=0.2)
            await wait_until(sim, lambda: sim.mode is Mode.ENGAGED, 1.0, "ENGAGED after the tap")
            margin = sim.daemon.config.safety.pedal_override_margin_pct
            await wait_until(
                sim,
                lambda: tap.first_pressed_s(tapped_s, margin) is not None,
                1.0,
                "the tap in the brake telemetry",
            )
        finally:
            await tap.close()
        seen_s = tap.first_pressed_s(tapped_s, margin)
        engaged_s = sim.modes.entered_s(Mode.ENGAGED, tapped_s)
        assert seen_s is not None and engaged_s is not None
        report("brake tap", {"telemetry -> ENGAGED": engaged_s - seen_s})
        assert 0.0 <= engaged_s - seen_s <= REACTION_LIMIT_S
        await twins.refresh()
        assert twins.steering_mode() is SteeringMode.POSITION
        assert twins.pc104_moving()  # steering stays automatic; only the speed went back
        assert sim.daemon.core.state.set_speed_mps is None


async def test_manual_override_hands_everything_back_within_a_cycle() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        pressed_s = time.monotonic()
        await sim.press("manual_override")
        figures = await latencies(
            sim,
            pressed_s,
            {
                "READY": lambda: sim.mode is Mode.READY,
                "steering RELEASE": lambda: twins.steering_mode() is SteeringMode.RELEASE,
                "PC104 STOP": lambda: twins.pc104_pattern() is MotionPattern.STOP,
            },
        )
        report("manual override", figures)
        assert max(figures.values()) <= REACTION_LIMIT_S, figures
        await wait_until(sim, lambda: twins.hl_state() is HighLevelState.STANDBY, 1.0, "HL STANDBY")
        await wait_until(sim, lambda: not twins.lamps() & Lamps.ENGAGED, 1.0, "lamp off")
        await holds(sim, lambda: sim.mode is Mode.READY, 0.3, "READY")


async def test_hands_on_the_wheel_are_an_override_not_a_fault() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        config = sim.daemon.config
        steering = (await twins.refresh())["steering"]
        held_rad = steering["wheel_angle_rad"] + math.radians(10.0) * steering["steering_ratio"]
        gripped_s = time.monotonic()
        await twins.act("hands", wheel_rad=held_rad)
        try:
            figures = await latencies(
                sim,
                gripped_s,
                {
                    "READY": lambda: sim.mode is Mode.READY,
                    "steering RELEASE": lambda: twins.steering_mode() is SteeringMode.RELEASE,
                    "PC104 STOP": lambda: twins.pc104_pattern() is MotionPattern.STOP,
                },
            )
            report("hands on the wheel", figures)
            assert max(figures.values()) <= config.safety.steer_override_dwell_s + 0.1, figures
            await holds(sim, lambda: sim.mode is Mode.READY, 0.5, "READY while the hands stay")
        finally:
            await twins.act("hands", wheel_rad=None)
        assert Mode.ERROR not in sim.modes.entered_after(gripped_s)
        assert not sim.daemon.status_document()["faults"]


async def test_unplugged_board_latches_error_until_override() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        config = sim.daemon.config
        unplugged_s = time.monotonic()
        await twins.act("unplug", board="steering")
        figures = await latencies(
            sim,
            unplugged_s,
            {
                "ERROR": lambda: sim.mode is Mode.ERROR,
                "brake applied": twins.brake_applied,
                "PC104 STOP": lambda: twins.pc104_pattern() is MotionPattern.STOP,
                "panel WARNING": lambda: bool(twins.lamps() & Lamps.WARNING),
            },
        )
        report("steering board unplugged", figures)
        staleness = config.staleness
        limit_s = min(staleness.steering_pot_max_age_s, staleness.actuator_board_max_age_s)
        assert figures["ERROR"] <= limit_s + 0.1, figures
        # The pot (in the steering telemetry, 50 ms limit) goes first, the board after it.
        await wait_until(
            sim,
            lambda: {"stale:steering.pot", "stale:board.steering"} <= sim.fault_keys(),
            1.0,
            "steering pot and board stale",
        )
        await twins.refresh()
        assert not twins.lamps() & Lamps.ENGAGED

        replugged_s = time.monotonic()
        await twins.act("replug", board="steering")
        await recover_to_ready(sim)
        await holds(sim, lambda: sim.mode is Mode.READY, 1.0, "READY without a new engage press")
        assert Mode.ENGAGED not in sim.modes.entered_after(replugged_s)
        await engage(sim)  # a new press engages again


async def test_silent_pc104_is_an_error_until_it_talks_and_override() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        dropped_s = time.monotonic()
        await twins.act("pc104_faults", drop_all=True)
        try:
            figures = await latencies(
                sim,
                dropped_s,
                {
                    "ERROR": lambda: sim.mode is Mode.ERROR,
                    "steering RELEASE": lambda: twins.steering_mode() is SteeringMode.RELEASE,
                    "brake applied": twins.brake_applied,
                },
            )
            report("PC104 silent", figures)
            limit_s = sim.daemon.config.staleness.pc104_status_max_age_s
            assert figures["ERROR"] <= limit_s + 0.1, figures
            assert "stale:pc104.status" in sim.fault_keys()
            await holds(sim, lambda: sim.mode is Mode.ERROR, 0.3, "ERROR while silent")
        finally:
            await twins.act("pc104_faults", drop_all=False)
        await recover_to_ready(sim)


async def test_link_errors_beyond_the_budget_fault_but_a_few_bad_frames_do_not() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        # Three corrupted board frames: a 30 ms gap, inside the 100 ms age limit.
        boards = sim.daemon.io.boards
        assert boards is not None
        throttle = boards.throttle
        crc_before = throttle.health().crc_errors
        corrupted_s = time.monotonic()
        await twins.act("corrupt", board="throttle", frames=3)
        await holds(sim, lambda: sim.mode is Mode.ENGAGED, 0.5, "ENGAGED through 3 bad frames")
        assert throttle.health().crc_errors - crc_before == 3
        assert sim.modes.since(corrupted_s) == [Mode.ENGAGED]

        # Every PC104 frame corrupted: the error budget runs out.
        await twins.act("pc104_faults", bad_crc=True)
        try:
            await wait_until(sim, lambda: sim.mode is Mode.ERROR, 2.0, "ERROR on bad CRCs")
            await wait_until(
                sim, lambda: "pc104_link_errors" in sim.fault_keys(), 2.0, "pc104_link_errors"
            )
            # The safe command leaves in the faulting cycle; the twin reads it a moment later.
            await wait_until(
                sim,
                lambda: twins.steering_mode() is not SteeringMode.POSITION,
                0.5,
                "steering handed back",
            )
        finally:
            await twins.act("pc104_faults", bad_crc=False)
        await recover_to_ready(sim)


async def test_killed_scanner_twin_is_stale_scan_input_and_an_error() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        killed_s = time.monotonic()
        # Powered off: listener and connection gone.
        await twins.act("scanner_power", side="left", on=False)
        figures = await latencies(
            sim,
            killed_s,
            {
                "ERROR": lambda: sim.mode is Mode.ERROR,
                "steering RELEASE": lambda: twins.steering_mode() is SteeringMode.RELEASE,
                "PC104 STOP": lambda: twins.pc104_pattern() is MotionPattern.STOP,
            },
        )
        report("scanner killed", figures)
        assert figures["ERROR"] <= sim.daemon.config.staleness.scan_max_age_s + 0.1, figures
        assert "stale:scan.left" in sim.fault_keys()
        inputs = sim.daemon.status_document()["inputs"]
        assert inputs["scan.left"]["stale"] and not inputs["scan.right"]["stale"]
        await holds(sim, lambda: sim.mode is Mode.ERROR, 0.5, "ERROR while the scanner is off")
        # Powered on again: the client reconnects, the fault clears, the mode stays latched.
        await twins.act("scanner_power", side="left", on=True)
        await recover_to_ready(sim)


async def test_crashed_control_service_restarts_safe_and_never_reengages(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        core = sim.daemon.core
        real_step, real_reset = core.step, core.reset
        crashes: list[float] = []
        modes_after_reset: list[Mode] = []

        def step_crashing_once(*args: Any, **kwargs: Any) -> CoreOutput:
            if not crashes:
                crashes.append(time.monotonic())
                raise RuntimeError("injected control crash")
            return real_step(*args, **kwargs)

        def recording_reset() -> None:
            real_reset()
            modes_after_reset.append(core.state.mode)

        monkeypatch.setattr(core, "reset", recording_reset)
        monkeypatch.setattr(core, "step", step_crashing_once)
        record = sim.daemon.supervisor.records["control"]
        patched_s = time.monotonic()
        figures = await latencies(
            sim,
            patched_s,
            {
                "brake 100 %": lambda: (
                    twins.brake_command() == BrakeCommand(enable=True, position_pct=100.0)
                ),
                "steering RELEASE": lambda: twins.steering_mode() is SteeringMode.RELEASE,
                "PC104 STOP": lambda: twins.pc104_pattern() is MotionPattern.STOP,
                "restart scheduled": lambda: record.budget.total_restarts == 1,
            },
        )
        assert crashes
        figures = {name: seconds - (crashes[0] - patched_s) for name, seconds in figures.items()}
        report("control crash", figures)
        await wait_until(sim, lambda: sim.mode is Mode.READY, READY_TIMEOUT_S, "READY again")
        assert modes_after_reset == [Mode.BOOT]
        assert record.state is ServiceState.RUNNING
        assert sim.daemon.supervisor.latched_error is None
        await holds(sim, lambda: sim.mode is Mode.READY, 2.0, "READY, not re-engaged")
        assert Mode.ENGAGED not in sim.modes.entered_after(crashes[0])
        await twins.refresh()
        assert twins.steering_mode() is not SteeringMode.POSITION


async def test_stuck_control_loop_withholds_watchdog_pings(
    monkeypatch: pytest.MonkeyPatch, notify_socket: FakeNotifySocket
) -> None:
    for key, value in notify_socket.environment(WATCHDOG_S).items():
        monkeypatch.setenv(key, value)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    release = asyncio.Event()
    hung_at: list[float] = []
    try:
        async with running_sim() as sim:
            twins = sim.twins
            await asyncio.to_thread(notify_socket.wait_for, "WATCHDOG=1", 5.0)
            await engage(sim)
            ticker = sim.daemon.control.ticker
            real_tick = ticker.tick

            async def tick_then_hang() -> float:
                if hung_at:
                    return await real_tick()
                hung_at.append(time.monotonic())
                while not release.is_set():  # neither beats nor lets itself be cancelled
                    with contextlib.suppress(asyncio.CancelledError):
                        await asyncio.sleep(0.01)
                raise asyncio.CancelledError

            sim.clean_exit_expected = False
            monkeypatch.setattr(ticker, "tick", tick_then_hang)
            await wait_until(sim, lambda: bool(hung_at), 1.0, "the control loop hung")
            record = sim.daemon.supervisor.records["control"]
            figures = await latencies(
                sim,
                hung_at[0],
                {
                    "HUNG": lambda: record.state is ServiceState.HUNG,
                    "steering latched": lambda: not twins.steering_commanded(),
                    "PC104 STOP": lambda: twins.pc104_applied() is MotionPattern.STOP,
                },
            )
            report("control loop stuck", figures)
            await asyncio.sleep(1.5)
            assert record.state is ServiceState.HUNG  # it never acknowledged the cancellation
            assert record.budget.total_restarts == 0
            deadline_s = sim.daemon.config.supervision.control_heartbeat_deadline_s
            pings = notify_socket.lines("WATCHDOG=1")
            last_after_hang_s = pings[-1].at_s - hung_at[0]
            print(f"[watchdog] last WATCHDOG=1 {last_after_hang_s * 1e3:.0f} ms after the hang")
            assert last_after_hang_s <= deadline_s + WATCHDOG_S / 2
            assert pings[-1].at_s < time.monotonic() - 2 * WATCHDOG_S  # systemd would fire
            assert any("DEGRADED" in m.line for m in notify_socket.lines("STATUS="))
            # The hung loop's leased commands ran out: the boards and the PC104 stopped.
            timeout_s = sim.daemon.config.safety.lower_layer_command_timeout_s
            limit_s = sim.daemon.control.lease_s + timeout_s + REACTION_LIMIT_S
            assert max(figures["steering latched"], figures["PC104 STOP"]) <= limit_s, figures
    finally:
        release.set()  # the real daemon exits hard here; the test lets the task end instead
    # The shutdown could not join the stuck task: the caller must end the process.
    assert sim.result is not None and sim.result.must_force_exit, sim.result


async def test_estop_latches_until_released_and_reset() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        await engage(sim)
        pushed_s = time.monotonic()
        await twins.act("estop", pressed=True)
        figures = await latencies(
            sim,
            pushed_s,
            {
                "ESTOP": lambda: sim.mode is Mode.ESTOP,
                "steering latched": lambda: not twins.steering_commanded(),
                "PC104 STOP": lambda: twins.pc104_pattern() is MotionPattern.STOP,
            },
        )
        report("e-stop", figures)
        await wait_until(
            sim, lambda: twins.brake_actuator_pct() >= 99.0, 2.0, "brake actuator at full"
        )
        output = sim.daemon.control.last_output
        assert output is not None
        assert output.brake == BrakeCommand(enable=True, position_pct=100.0)
        await wait_until(sim, lambda: bool(twins.lamps() & Lamps.WARNING), 1.0, "warning lamp")

        for _ in range(2):
            await sim.press("manual_override")
            await holds(
                sim, lambda: sim.mode is Mode.ESTOP, 0.3, "ESTOP while the mushroom is down"
            )
        await twins.act("estop", pressed=False)
        await holds(sim, lambda: sim.mode is Mode.ESTOP, 0.3, "ESTOP latched after the release")
        released_s = time.monotonic()
        await sim.press("manual_override")
        await wait_until(sim, lambda: sim.mode is Mode.READY, LIVENESS_TIMEOUT_S, "READY")
        assert Mode.ENGAGED not in sim.modes.entered_after(released_s)
        await wait_until(
            sim, lambda: not twins.lamps() & Lamps.WARNING, 1.0, "warning lamp off in READY"
        )


async def _dbw(command: click.Command, *args: str) -> Result:
    """Run a `dbw` subcommand as the CLI would, in a thread (it runs an event loop of its own).

    In-process rather than a new interpreter: starting Python competes with the daemon for
    the machine's two cores, and the steering pot's age limit is 50 ms.
    """
    return await asyncio.to_thread(CliRunner().invoke, command, list(args))


def printed_document(stdout: str) -> dict[str, Any]:
    """The indented document `dbw status --json` printed. The daemon runs in this process
    and its log lines (one JSON object per line) share the captured stdout."""
    lines = stdout.splitlines()
    start = lines.index("{")
    doc: dict[str, Any] = json.loads("\n".join(lines[start : lines.index("}", start) + 1]))
    return doc


async def test_status_and_engage_through_the_control_socket() -> None:
    async with running_sim() as sim:
        twins = sim.twins
        path = sim.socket_path
        await wait_until(
            sim, lambda: not sim.daemon.status_document()["faults"], 2.0, "no faults in READY"
        )
        result = await _dbw(status_command, "--json", "--socket", path)
        assert result.exit_code == 0, result.output
        doc = printed_document(result.stdout)
        assert doc["mode"] == "ready"
        assert doc["faults"] == []
        for name in ("board.steering", "board.brake", "pc104.status", "scan.left"):
            entry = doc["inputs"][name]
            assert entry["critical"] and not entry["stale"], (name, entry)
            assert 0.0 <= entry["age_s"] <= entry["limit_s"], (name, entry)

        reply = await query(path, {"op": "command", "name": "engage"})
        assert reply == {"ok": True, "accepted": True, "message": "ready -> engaged"}
        await wait_until(
            sim, lambda: twins.steering_mode() is SteeringMode.POSITION, 1.0, "steering POSITION"
        )
        status = await query(path, {"op": "status"})
        assert status["status"]["mode"] == "engaged"
        reply = await query(path, {"op": "command", "name": "disengage"})
        assert reply["accepted"], reply
        await wait_until(sim, lambda: sim.mode is Mode.READY, 1.0, "READY")

        # A foot on the brake in READY: refused, and the reason says so.
        await twins.act("pedal", pedal="brake", pct=30.0)
        await wait_until(
            sim, lambda: sim.daemon.status_document()["overrides"]["brake_pedal"], 1.0, "pedal"
        )
        result = await _dbw(engage_command, "--socket", path)
        assert result.exit_code == 1, result.output
        assert "engage: refused" in result.stderr, result.output
        assert "operator overriding" in result.stderr, result.output
        await twins.act("pedal", pedal="brake", pct=0.0)
        assert sim.mode is Mode.READY

        await twins.act("unplug", board="brake")
        await wait_until(sim, lambda: sim.mode is Mode.ERROR, 2.0, "ERROR, brake unplugged")
        reply = await query(path, {"op": "command", "name": "engage"})
        assert reply["ok"] and reply["accepted"] is False, reply
        assert "cannot engage from error" in reply["message"]
        result = await _dbw(engage_command, "--socket", path)
        assert result.exit_code == 1, result.output
        assert "engage: refused" in result.stderr, result.output
        assert "cannot engage from error" in result.stderr, result.output
        status = (await query(path, {"op": "status"}))["status"]
        assert status["mode"] == "error"
        assert "stale:board.brake" in {fault["key"] for fault in status["faults"]}
        assert status["inputs"]["board.brake"]["stale"]
        await twins.act("replug", board="brake")


async def test_cli_names_a_refusal_once() -> None:
    async with running_sim() as sim:
        await sim.twins.act("pedal", pedal="brake", pct=30.0)
        await wait_until(
            sim, lambda: sim.daemon.status_document()["overrides"]["brake_pedal"], 1.0, "pedal"
        )
        result = await _dbw(engage_command, "--socket", sim.socket_path)
        assert result.exit_code == 1, result.output
        assert result.stderr == "engage: refused: operator overriding\n"


_IMPORTS_AFTER_READY = """
import asyncio, json, os, shutil, socket, sys, tempfile, time, uuid
from appliance.config import load_config
from appliance.daemon import Daemon
from appliance.logs import configure_logging
from appliance.modes import Mode

configure_logging("warning", stream=sys.stderr, json=True)


def free_port():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


async def main():
    config = load_config("sim")
    d = config.devices
    devices = d.model_copy(update={
        "can": d.can.model_copy(update={"channel": "dbw-imports-" + uuid.uuid4().hex[:8]}),
        "lms111_left": d.lms111_left.model_copy(update={"port": free_port()}),
        "lms111_right": d.lms111_right.model_copy(update={"port": free_port()}),
    })
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")
    daemon = Daemon(
        config.model_copy(update={"devices": devices}),
        control_socket=os.path.join(directory, "control.sock"),
    )
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    deadline_s = time.monotonic() + 10.0
    while daemon.core.state.mode is not Mode.READY and time.monotonic() < deadline_s:
        await asyncio.sleep(0.01)
    before = set(sys.modules)
    worst_stall_s = 0.0
    end_s = time.monotonic() + 2.0 / config.rates.status_report_hz
    while time.monotonic() < end_s:
        started_s = time.monotonic()
        await asyncio.sleep(0.002)
        worst_stall_s = max(worst_stall_s, time.monotonic() - started_s - 0.002)
    imported = sorted(set(sys.modules) - before)
    faults = [r.key for r in daemon.core.faults.history]
    daemon.request_stop("done")
    await run
    shutil.rmtree(directory, ignore_errors=True)
    print(json.dumps({"imported": imported, "worst_stall_s": worst_stall_s, "faults": faults}))


asyncio.run(main())
"""


async def test_nothing_is_imported_on_the_event_loop_after_ready() -> None:
    # A fresh interpreter, so imports done by the test process do not hide a lazy one.
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        _IMPORTS_AFTER_READY,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 60.0)
    assert proc.returncode == 0, err.decode()
    result = json.loads(out.decode().splitlines()[-1])
    print(f"[imports] after READY: {result}")
    assert result["imported"] == [], result
