"""The PC104 client against the twin on python-can's ``virtual`` bus, in one process.

Each test gets its own virtual channel, runs the real asyncio client and the real twin
(which steps its own simulated vehicle in real time), injects one fault and checks what
the daemon would see: health figures, topics, the vehicle's reaction and the logs (each
failure logged once per episode, never per frame). Waits are short and bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import itertools
import os
import time
import uuid
from collections.abc import AsyncIterator, Callable, MutableMapping, Sequence
from typing import Any

import can
import pytest
from can.interfaces.virtual import VirtualBus
from structlog.testing import capture_logs

from appliance.config import load_config, parts
from appliance.config.models import CanEndpoint
from appliance.sim.twins.pc104 import Pc104Twin
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.pc104.client import Pc104Client
from drivers.pc104.endpoint import CanInterface
from drivers.pc104.errorframes import BusCondition
from drivers.pc104.link import bus_factory
from drivers.pc104.messages import (
    ControlSource,
    HlExpectedPose,
    HlPose,
    MotionCommand,
    MotionPattern,
    Pc104Status,
    PoseState,
    SteeringLoop,
)
from drivers.topics import Topic

pytestmark = pytest.mark.timeout(30)

STOP = MotionCommand.stop()
FORWARD = MotionCommand(MotionPattern.STRAIGHT, 1.0)
PERIOD_S = 0.02
MAX_AGE_S = 0.1


async def wait_until(condition: Callable[[], bool], timeout_s: float = 2.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what or condition}")
        await asyncio.sleep(0.005)


class FlakySwitch:
    """Makes every send of the client's buses fail with ``errno`` while set."""

    def __init__(self) -> None:
        self.errno: int | None = None
        self.opened = 0


class FlakyBus(VirtualBus):
    def __init__(self, channel: str, switch: FlakySwitch) -> None:
        super().__init__(channel=channel)
        self.switch = switch

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        code = self.switch.errno
        if code is not None:
            raise can.CanOperationError(f"Failed to transmit: {os.strerror(code)}", code)
        super().send(msg, timeout)


class Rig:
    def __init__(self, switch: FlakySwitch | None = None) -> None:
        self.channel = f"pc104-{uuid.uuid4().hex[:12]}"
        self.config = load_config("sim")
        self.world = SimWorld(VehicleParams.from_config(self.config))
        endpoint = CanEndpoint(interface=CanInterface.VIRTUAL, channel=self.channel)
        self.twin = Pc104Twin(bus_factory(endpoint), self.world, emit_error_frames=True)
        open_bus = bus_factory(endpoint)
        if switch is not None:

            def open_bus() -> can.BusABC:
                switch.opened += 1
                return FlakyBus(self.channel, switch)

        self.client = Pc104Client(
            parts.pc104_client_params(self.config), self.config.devices.can, open_bus=open_bus
        )
        self.beats: list[float] = []
        self.tasks: list[asyncio.Task[None]] = []

    async def start(self) -> None:
        self.tasks.append(asyncio.create_task(self.twin.run()))
        self.tasks.append(asyncio.create_task(self.client.run(self._beat)))
        await wait_until(lambda: self.client.health().peer_ready, what="the PC104 ready")

    def _beat(self) -> None:
        self.beats.append(time.monotonic())

    async def stop_client(self) -> None:
        task = self.tasks.pop()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    async def close(self) -> None:
        for task in self.tasks:
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)

    async def drive(self, command: MotionCommand, seconds: float) -> None:
        """Play the control loop: send ``command`` every period for ``seconds``."""
        end_s = time.monotonic() + seconds
        while time.monotonic() < end_s:
            self.client.send_command(command)
            await asyncio.sleep(PERIOD_S / 2)

    def status_fresh(self) -> bool:
        return not self.client.health().stale


@pytest.fixture
async def rig() -> AsyncIterator[Rig]:
    r = Rig()
    await r.start()
    yield r
    await r.close()


def events(logs: Sequence[MutableMapping[str, Any]], name: str) -> list[MutableMapping[str, Any]]:
    return [entry for entry in logs if entry["event"] == name]


async def test_status_and_measurements_flow_to_the_topics(rig: Rig) -> None:
    await asyncio.sleep(1.1)
    health = rig.client.health()
    assert health.connected and not health.stale
    assert health.control_source is ControlSource.AUTOMATIC
    assert 140 < health.frames_in_per_s < 200  # 3 x 50 Hz + 2 x 10 Hz
    assert 50 < health.frames_out_per_s < 70  # 50 Hz command + 10 Hz heartbeat
    assert (health.crc_errors, health.counter_errors, health.send_drops) == (0, 0, 0)
    topics = rig.client.topics
    now_s = time.monotonic()
    fast: list[Topic[Any]] = [topics.status, topics.wheel_angles, topics.motor_pulses]
    slow: list[Topic[Any]] = [topics.inclinometer, topics.heartbeat]
    # Fresh, not punctual: the rates above say 50 and 10 Hz; an age or a beat gap says the
    # data and the beats keep coming, and a loaded machine stalls a loop by tens of ms
    # (25 ms seen in the soaks), so the bounds are a few periods, not one.
    for topic in fast:
        assert topic.age_s(now_s) < 0.2, topic.name
    for topic in slow:
        assert topic.age_s(now_s) < 0.4, topic.name
    beat_gaps = [b - a for a, b in itertools.pairwise(rig.beats)]
    assert max(beat_gaps) < 0.25


async def test_commands_move_the_simulated_vehicle(rig: Rig) -> None:
    await rig.drive(FORWARD, 1.5)
    assert rig.world.state.x_m > 0.3
    sample = rig.client.topics.status.latest()
    assert sample is not None
    assert sample.value.active_pattern is MotionPattern.STRAIGHT
    assert sample.value.measured_speed_mps > 0.5
    pulses = rig.client.topics.motor_pulses.latest()
    assert pulses is not None and pulses.value.front_left_counts > 30  # 100 pulses/m
    await rig.drive(MotionCommand(MotionPattern.FRONT_STEER, 0.5, front_steer_rad=0.2), 1.0)
    wheels = rig.client.topics.wheel_angles.latest()
    assert wheels is not None and wheels.value.front_rad > 0.1
    assert rig.world.state.yaw_rad > 0.01  # turning left


async def test_the_pose_frames_go_out_with_the_commands_while_they_are_refreshed(
    rig: Rig,
) -> None:
    """HL_Pose and HL_ExpectedPose follow each command; when the pose stops coming while
    the plan goes on, the twin, steering on pose, stops the vehicle and says why."""
    expected = HlExpectedPose(-6.0, 0.0, 0.0, SteeringLoop.PC104)
    command = MotionCommand(MotionPattern.REAR_STEER, 0.3)
    end_s = time.monotonic() + 1.0
    while time.monotonic() < end_s:
        state = rig.world.state
        rig.client.send_command(command)
        rig.client.send_pose(HlPose(state.x_m, state.y_m, state.yaw_rad, PoseState.OK), expected)
        await asyncio.sleep(PERIOD_S / 2)
    core = rig.twin.core
    assert core.expected_pose == expected and core.pose is not None
    assert core.closing_pose_loop(time.monotonic())
    assert rig.world.state.speed_mps > 0.1 and not core.pose_fault
    counts = core.monitors[HlPose].counts
    assert counts.accepted >= 30 and counts.counter_errors == 0
    # Commands and the plan go on, the pose no longer comes: the twin must not steer blind.
    end_s = time.monotonic() + 0.5
    while time.monotonic() < end_s:
        rig.client.send_command(command)
        rig.client.send_pose(None, expected)
        await asyncio.sleep(PERIOD_S / 2)
    assert core.pose_fault
    assert rig.world.command.pattern is MotionPattern.STOP
    await wait_until(lambda: _pose_fault_reported(rig), 1.0, "FaultPose in the status")
    # A plan no longer refreshed by the control loop stops going out too.
    await rig.drive(STOP, 0.3)
    assert not core.closing_pose_loop(time.monotonic())


def _pose_fault_reported(rig: Rig) -> bool:
    sample = rig.client.topics.status.latest()
    return sample is not None and sample.value.faults.pose


async def test_dropped_status_is_stale_within_one_period_of_the_limit(rig: Rig) -> None:
    with capture_logs() as logs:
        driving = asyncio.create_task(rig.drive(FORWARD, 1.2))
        await asyncio.sleep(0.5)
        rig.twin.faults.drop_all = True
        await wait_until(lambda: rig.client.health().stale, 1.0, "stale status")
        health = rig.client.health()
        last_s = rig.client.monitors[0x110].last_accepted_s
        assert health.stale_since_s is not None and last_s is not None
        assert MAX_AGE_S < health.stale_since_s - last_s <= MAX_AGE_S + PERIOD_S
        await driving
        assert rig.client.health().holding_stop  # STOP went out instead of FORWARD
        assert rig.world.command.pattern is MotionPattern.STOP
        rig.twin.faults.drop_all = False
        await wait_until(rig.status_fresh, 1.0, "status back")
        assert rig.client.health().holding_stop  # until the control loop sends STOP
        await rig.drive(STOP, 0.1)
        assert not rig.client.health().holding_stop
    assert len(events(logs, "pc104_status_stale")) == 1
    assert len(events(logs, "pc104_status_stale_ended")) == 1
    assert len(events(logs, "pc104_holding_stop")) == 1


async def test_bad_crc_is_counted_and_survived(rig: Rig) -> None:
    with capture_logs() as logs:
        rig.twin.faults.bad_crc = True
        await asyncio.sleep(0.2)
        rig.twin.faults.bad_crc = False
        await wait_until(lambda: rig.client.health().stale is False, 1.0)
        # Each message's episode ends when its error budget has drained, one good frame
        # per error: for the 10 Hz messages four or five frames (0.3-0.5 s) after the
        # status is fresh, by their phase (a fixed 0.3 s wait saw 3 of 5 end, once).
        await wait_until(
            lambda: len(events(logs, "pc104_receive_errors_ended")) >= 5,
            2.0,
            "an end to every message's receive errors",
        )
    health = rig.client.health()
    assert health.crc_errors >= 15
    assert health.connected and health.reconnects == 0
    status_logs = [e for e in events(logs, "pc104_receive_errors") if e.get("reason") == "crc"]
    assert len(status_logs) == 5  # one per PC104 message, not one per frame
    assert len(events(logs, "pc104_receive_errors_ended")) == 5


async def test_stuck_counter_is_counted_and_not_trusted(rig: Rig) -> None:
    rig.twin.faults.stuck_counter = True
    await wait_until(lambda: rig.client.health().stale, 1.0, "stale on a stuck counter")
    assert rig.client.monitors[0x110].counts.stuck >= 3
    rig.twin.faults.stuck_counter = False
    await wait_until(rig.status_fresh, 1.0, "status back")
    assert rig.client.health().counter_errors >= 3


async def test_delayed_frames_count_as_late_without_counter_errors(rig: Rig) -> None:
    rig.twin.faults.delay_s = 0.15
    await wait_until(lambda: rig.client.health().stale, 1.0, "a gap longer than the limit")
    await wait_until(rig.status_fresh, 1.0, "delayed frames flowing")
    health = rig.client.health()
    assert health.late_frames >= 3
    assert health.counter_errors == 0


async def test_bus_off_and_error_passive_are_reported_and_cleared(rig: Rig) -> None:
    with capture_logs() as logs:
        driving = asyncio.create_task(rig.drive(FORWARD, 1.0))
        await asyncio.sleep(0.3)
        rig.twin.faults.bus_off = True
        await wait_until(lambda: rig.client.health().bus_condition is BusCondition.BUS_OFF)
        await wait_until(lambda: rig.client.health().stale)
        await driving
        assert rig.world.command.pattern is MotionPattern.STOP  # the twin heard nothing
        rig.twin.faults.bus_off = False
        await wait_until(lambda: rig.client.health().bus_condition is BusCondition.ACTIVE)
        await wait_until(rig.status_fresh)
        rig.twin.faults.error_passive = True
        await wait_until(lambda: rig.client.health().bus_condition is BusCondition.PASSIVE)
        assert rig.status_fresh()  # error passive still transmits
        rig.twin.faults.error_passive = False
        await wait_until(lambda: rig.client.health().bus_condition is BusCondition.ACTIVE)
    assert [e["condition"] for e in events(logs, "pc104_bus_error_state")] == [
        "BUS_OFF",
        "PASSIVE",
    ]
    assert len(events(logs, "pc104_bus_error_state_ended")) == 2


async def test_cab_takeover_shows_in_the_status_and_stops_commanding(rig: Rig) -> None:
    driving = asyncio.create_task(rig.drive(FORWARD, 0.8))
    await asyncio.sleep(0.3)
    rig.twin.faults.cab_control = True
    await wait_until(lambda: rig.client.health().control_source is ControlSource.CAB)
    await driving
    health = rig.client.health()
    assert not health.peer_ready and health.holding_stop and not health.stale
    assert "pc104" not in rig.world._inputs  # the cab's controls act, not the PC104's


async def test_a_restarted_twin_is_resynced(rig: Rig) -> None:
    status = rig.client.monitors[0x110]
    driving = asyncio.create_task(rig.drive(FORWARD, 1.0))
    # A reboot restarts the counters at 0; make sure that is a visible jump for the status
    # (from 15 it would look like the next frame, which needs no resync at all).
    await wait_until(lambda: 4 <= rig.twin.core.next_counter(Pc104Status) <= 12)
    with capture_logs() as logs:
        rig.twin.restart()
        await wait_until(lambda: status.counts.resyncs == 1, 1.0, "the status resynced")
        await asyncio.sleep(0.1)
        assert rig.status_fresh()
        sample = rig.client.topics.status.latest()
        assert sample is not None and sample.value.stop_required  # rebooted: waits for STOP
        assert rig.world.command.pattern is MotionPattern.STOP
        await driving
        await rig.drive(STOP, 0.15)  # the control loop re-arms the PC104
        await wait_until(lambda: rig.client.health().peer_ready)
    jumps = [e for e in events(logs, "pc104_receive_errors") if e.get("reason") == "resyncing"]
    assert "PC104_Status" in [e["message"] for e in jumps]
    assert status.counts.jumps == 1


async def test_the_twin_brakes_100_ms_after_commands_stop(rig: Rig) -> None:
    """Over the link, with the client gone, the twin brakes by its own command timeout.

    The exact 100 ms is test_twin_core's, on a fake clock. Here the client is cancelled in
    the step that gave it its last command: a client left running 100 ms past that sends
    STOP itself (its own timeout), and the twin would then brake because it was told to
    (census run 6 of issue 9: its log has ``pc104_holding_stop`` 20 ms before the client
    stopped, and the twin braked 18 ms after that accepted STOP). How soon after 100 ms
    is the machine's business, so the upper bound only says "promptly".
    """
    await rig.drive(FORWARD, 1.0)
    assert rig.world.state.speed_mps > 0.3
    rig.client.send_command(FORWARD)
    await rig.stop_client()
    await wait_until(lambda: rig.world.command.pattern is MotionPattern.STOP, 2.0)
    braked_s = time.monotonic()
    last = rig.twin.core.command
    assert last is not None and last.pattern is FORWARD.pattern  # not told to stop
    last_command_s = rig.twin.core.command_monitor.last_accepted_s
    assert last_command_s is not None
    assert MAX_AGE_S <= braked_s - last_command_s < MAX_AGE_S + 1.0
    assert rig.world.command.brake_pct == 100.0
    await wait_until(lambda: rig.world.state.speed_mps == 0.0, 2.0, "vehicle at rest")


async def test_no_buffer_space_drops_frames_and_logs_once_per_episode() -> None:
    switch = FlakySwitch()
    rig = Rig(switch)
    await rig.start()
    try:
        with capture_logs() as logs:
            for episode in (1, 2):
                switch.errno = errno.ENOBUFS
                await asyncio.sleep(0.3)
                switch.errno = None
                # The next send ends the episode; a stall must not merge the two episodes.
                await wait_until(
                    lambda n=episode: len(events(logs, "pc104_send_drops_ended")) >= n,
                    2.0,
                    f"the end of send-drop episode {episode}",
                )
        health = rig.client.health()
        assert health.send_drops >= 25
        assert health.connected and health.reconnects == 0 and switch.opened == 1
        assert "No buffer space" in health.last_error
        assert len(events(logs, "pc104_send_drops")) == 2
        assert len(events(logs, "pc104_send_drops_ended")) == 2
    finally:
        await rig.close()


async def test_a_lost_interface_is_reopened_with_backoff_without_blocking() -> None:
    switch = FlakySwitch()
    rig = Rig(switch)
    await rig.start()
    try:
        with capture_logs() as logs:
            switch.errno = errno.ENETDOWN  # what socketcan raises once the link is down
            await wait_until(lambda: switch.opened >= 4, 2.0, "reopen attempts")
            assert not rig.client.health().connected or switch.opened >= 4
            switch.errno = None
            await wait_until(lambda: rig.client.health().connected and rig.status_fresh(), 2.0)
        assert rig.client.health().reconnects >= 3
        assert len(events(logs, "pc104_link_down")) == 1
        assert len(events(logs, "pc104_link_down_ended")) == 1
        beat_gaps = [b - a for a, b in itertools.pairwise(rig.beats)]
        assert max(beat_gaps) < 0.1  # the supervisor never sees a hang
    finally:
        await rig.close()
