"""The simulated PC104 lower-level controller, sans I/O: frames in, frames out, time given.

It behaves like the controller Qian et al. describe (section 2.2.2): it selects the motion
pattern the high level asks for and runs a PID speed loop for it on the simulated
vehicle, and it reports what the vehicle does. It honours the same DBC with the same
rules as the client: commands with a bad length, CRC or counter are dropped and counted,
and it stops the vehicle 100 ms after the last valid command. After such a stop, and when
the cab or remote takes over, it holds the vehicle until it receives a STOP command in
automatic control (``StopRequired``): motion never resumes just because frames do.
When the high level asks it to close the steering loop itself (HL_ExpectedPose with
SteeringLoop = PC104), it steers STRAIGHT, OBLIQUE and REAR_STEER from HL_Pose and the
expected pose (:mod:`.pc104_pose_loop`), and stops the same way (``FaultPose``) the moment
that pose is missing for 100 ms or not OK: it never steers blind.

Fault injection (:class:`TwinFaults`) acts on what the twin transmits, the way a
misbehaving controller or bus would show up at the client. ``bus_off`` and
``error_passive`` cannot be produced on a ``virtual`` bus (it has no controller), so when
``emit_error_frames`` is set the twin sends the SocketCAN error frame the client's own
controller would deliver (CAN_ERR_BUSOFF, then CAN_ERR_RESTARTED on recovery). That is a
simulation shortcut: on a real bus the frame comes from the local controller, and on vcan
(which has no error states) the twin simply goes silent.
"""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

from appliance.sim.twins.pc104_pose_loop import POSE_PATTERNS, PoseLoop, PoseLoopParams
from appliance.sim.world import SimWorld
from drivers.geometry import Pose2D
from drivers.pc104 import protocol
from drivers.pc104.errorframes import BusCondition, error_frame
from drivers.pc104.messages import (
    PULSE_COUNTER_MODULO,
    ControlSource,
    HighLevelState,
    HlExpectedPose,
    HlHeartbeat,
    HlPose,
    Inclinometer,
    Message,
    MotionCommand,
    MotionPattern,
    MotorPulses,
    Pc104Faults,
    Pc104Heartbeat,
    Pc104Message,
    Pc104State,
    Pc104Status,
    PoseState,
    SteeringLoop,
    WheelAngles,
)
from drivers.pc104.monitor import MonitorParams, ReceiveMonitor, RxVerdict

WORLD_SOURCE = "pc104"  # the twin's slot in SimWorld.set_inputs
_ROW_LIMIT_RAD = 1.57
_SPEED_LIMIT_MPS = 10.0
_TILT_LIMIT_RAD = 0.5236
_DECODED_FRAMES = 64  # a held command and the heartbeat, every counter value: 32
# The HL's frames the twin checks for counter continuity, each with its own monitor.
_MONITORED = (MotionCommand, HlPose, HlExpectedPose)


class OutFrame(NamedTuple):
    arbitration_id: int
    data: bytes
    is_error_frame: bool = False


@dataclass(frozen=True)
class PidGains:
    kp_pct_per_mps: float = 60.0
    ki_pct_per_m: float = 20.0
    integral_limit_pct: float = 10.0
    brake_pct_per_mps: float = 80.0  # braking when faster than asked
    standstill_mps: float = 0.02


class PidSpeedController:
    """Speed PID of one motion pattern: signed setpoint in, throttle/brake/reverse out."""

    def __init__(self, gains: PidGains = PidGains()) -> None:
        self.gains = gains
        self.integral_pct = 0.0

    def reset(self) -> None:
        self.integral_pct = 0.0

    def update(
        self, setpoint_mps: float, measured_mps: float, dt_s: float
    ) -> tuple[float, float, bool]:
        g = self.gains
        reverse = setpoint_mps < 0
        direction = -1.0 if reverse else 1.0
        along_mps = measured_mps * direction  # speed in the wanted direction
        if abs(setpoint_mps) < g.standstill_mps or along_mps < -g.standstill_mps:
            self.reset()  # hold still, or stop before driving the other way
            return 0.0, 100.0, reverse
        error_mps = abs(setpoint_mps) - along_mps
        self.integral_pct += g.ki_pct_per_m * error_mps * dt_s
        self.integral_pct = max(-g.integral_limit_pct, min(g.integral_limit_pct, self.integral_pct))
        u_pct = g.kp_pct_per_mps * error_mps + self.integral_pct
        if u_pct >= 0:
            return min(u_pct, 100.0), 0.0, reverse
        return 0.0, min(-error_mps * g.brake_pct_per_mps, 100.0), reverse


@dataclass
class TwinFaults:
    """Switches a test flips while the twin runs; all off = a healthy controller."""

    drop_all: bool = False  # transmit nothing (frames lost on the way)
    drop_one_in: int = 0  # drop every n-th frame (0 = none)
    delay_s: float = 0.0  # hold every frame this long before it goes out
    bad_crc: bool = False  # corrupt the CRC of every frame
    stuck_counter: bool = False  # repeat the same counter value
    bus_off: bool = False  # neither transmit nor receive
    error_passive: bool = False  # keep working, report the error-passive state
    cab_control: bool = False  # the cab operator has taken over


@dataclass(frozen=True)
class TwinParams:
    command_max_age_s: float = 0.1
    pulses_per_m: float = 100.0
    inclinometer_noise_rad: float = 0.0005
    gains: PidGains = field(default_factory=PidGains)
    pose_loop: PoseLoopParams = field(default_factory=PoseLoopParams)


class Pc104TwinCore:
    def __init__(
        self,
        world: SimWorld,
        params: TwinParams = TwinParams(),
        faults: TwinFaults | None = None,
        *,
        emit_error_frames: bool = False,
        seed: int = 0,
        now_s: float = 0.0,
    ) -> None:
        self.world = world
        self.params = params
        self.faults = faults if faults is not None else TwinFaults()
        self.emit_error_frames = emit_error_frames
        self._rng = random.Random(seed)
        self.pid = PidSpeedController(params.gains)
        self.pose_loop = PoseLoop(params.pose_loop)
        self.monitors = {
            t: ReceiveMonitor(
                MonitorParams(protocol.spec_for(t).period_s, params.command_max_age_s)
            )
            for t in _MONITORED
        }
        self.command_monitor = self.monitors[MotionCommand]
        self.restarts = -1  # restart() counts the first boot as 0
        # per message type: the last message and its frames by counter (see _encode)
        self._encoded: dict[type, tuple[Pc104Message, dict[int, tuple[int, bytes]]]] = {}
        self._decoded: dict[tuple[int, bytes], tuple[Message, int]] = {}  # see _decode
        self.restart(now_s)

    def restart(self, now_s: float) -> None:
        """A reboot of the controller: counters from 0, STOP required, nothing remembered."""
        self.pid.reset()
        self.pose_loop.reset()
        for monitor in self.monitors.values():
            monitor.reset()
        self.boot_s = now_s
        self.command: MotionCommand | None = None
        self.pose: HlPose | None = None
        self.expected_pose: HlExpectedPose | None = None
        self.pose_fault = False  # closing the loop on pose without a usable pose
        self.control_source = ControlSource.AUTOMATIC
        self.stop_required = True
        self.applied_pattern = MotionPattern.STOP
        self.hl_state: HighLevelState | None = None  # from the last HL_Heartbeat heard
        self.bad_command_frames = 0
        self.last_invalid_s = -math.inf
        self.frames_sent = 0
        self.restarts += 1
        self._counters = {spec.frame_id: 0 for spec in protocol.SPECS.values()}
        self._due_s = {t: now_s for t in _TRANSMITTED}
        self._delayed: deque[tuple[float, OutFrame]] = deque()
        self._condition = BusCondition.ACTIVE
        self._last_tick_s = now_s

    def next_counter(self, message_type: type) -> int:
        """The counter the next frame of ``message_type`` will carry."""
        return self._counters[protocol.spec_for(message_type).frame_id]

    # ---- receiving --------------------------------------------------------------------
    def on_frame(self, arbitration_id: int, data: bytes, now_s: float) -> None:
        if self.faults.bus_off or arbitration_id not in protocol.HL_IDS:
            return
        try:
            message, counter = self._decode(arbitration_id, data, now_s)
        except protocol.Pc104ProtocolError:
            self._invalid(now_s, arbitration_id)
            return
        if isinstance(message, HlHeartbeat):
            # Liveness only (the command timeout is what stops us); kept for the bench.
            self.hl_state = message.state
            return
        if not isinstance(message, MotionCommand | HlPose | HlExpectedPose):
            return
        verdict = self.monitors[type(message)].update(now_s, counter)
        if verdict is RxVerdict.ACCEPTED:
            if isinstance(message, MotionCommand):
                self.command = message
            elif isinstance(message, HlPose):
                self.pose = message
            else:
                self.expected_pose = message
        elif verdict is not RxVerdict.RESYNCING:
            self._invalid(now_s, None)

    def _decode(self, arbitration_id: int, data: bytes, now_s: float) -> tuple[Message, int]:
        """`protocol.decode`'s message and counter, remembered for frames seen before.

        The high level repeats its frames (a held command with its counter cycling through
        16 values, the heartbeat): a frame already decoded is the same message again. Only
        valid frames are remembered, and at most `_DECODED_FRAMES` of them.
        """
        key = (arbitration_id, bytes(data))
        decoded = self._decoded.get(key)
        if decoded is None:
            frame = protocol.decode(arbitration_id, data, now_s)  # raises for a bad frame
            if len(self._decoded) >= _DECODED_FRAMES:
                self._decoded.clear()
            decoded = self._decoded[key] = (frame.message, frame.counter)
        return decoded

    def _invalid(self, now_s: float, arbitration_id: int | None) -> None:
        self.bad_command_frames = (self.bad_command_frames + 1) % 256
        self.last_invalid_s = now_s
        for message_type, monitor in self.monitors.items():
            if arbitration_id == protocol.spec_for(message_type).frame_id:
                monitor.record_invalid(now_s)

    # ---- one step of the controller ---------------------------------------------------
    def tick(self, now_s: float) -> list[OutFrame]:
        """Apply the command to the world and return the frames due by ``now_s``."""
        dt_s = max(now_s - self._last_tick_s, 0.0)
        self._last_tick_s = now_s
        self._control(now_s, dt_s)
        out = self._condition_frames()
        if not self.faults.bus_off:
            for message_type in _TRANSMITTED:
                if now_s >= self._due_s[message_type]:
                    period_s = protocol.spec_for(message_type).period_s
                    due_s = self._due_s[message_type] + period_s
                    self._due_s[message_type] = due_s if due_s > now_s else now_s + period_s
                    self._queue(self._build(message_type, now_s), now_s)
        while self._delayed and self._delayed[0][0] <= now_s:
            out.append(self._delayed.popleft()[1])
        return out

    def command_fresh(self, now_s: float) -> bool:
        return self.command is not None and not self.command_monitor.stale(now_s)

    def closing_pose_loop(self, now_s: float) -> bool:
        """The HL asks this controller to steer on pose (a fresh HL_ExpectedPose says so)."""
        expected = self.expected_pose
        return (
            expected is not None
            and expected.loop is SteeringLoop.PC104
            and not self.monitors[HlExpectedPose].stale(now_s)
        )

    def _pose_usable(self, now_s: float) -> bool:
        pose = self.pose
        return (
            pose is not None
            and pose.state is PoseState.OK
            and not self.monitors[HlPose].stale(now_s)
        )

    def _control(self, now_s: float, dt_s: float) -> None:
        source = ControlSource.CAB if self.faults.cab_control else ControlSource.AUTOMATIC
        if source is not self.control_source:
            self.control_source = source
            self.stop_required = True
            if source is not ControlSource.AUTOMATIC:  # the cab's controls act directly
                self.world.clear_inputs(WORLD_SOURCE)
        if source is not ControlSource.AUTOMATIC:
            self.applied_pattern = MotionPattern.STOP
            return
        command = self.command if self.command_fresh(now_s) else None
        pose_loop = (
            command is not None
            and command.pattern in POSE_PATTERNS
            and self.closing_pose_loop(now_s)
        )
        if command is None:
            self.stop_required = True
        elif command.pattern is MotionPattern.STOP:
            self.stop_required = False
            self.pose_fault = False
        if pose_loop and not self._pose_usable(now_s):
            self.pose_fault = self.stop_required = True  # steering blind: stop, wait for STOP
        if command is None or self.stop_required or command.pattern is MotionPattern.STOP:
            self.applied_pattern = MotionPattern.STOP
            self.pid.reset()
            self.pose_loop.reset()
            self.world.set_inputs(
                WORLD_SOURCE,
                pattern=MotionPattern.STOP,
                front_steer_rad=0.0,
                rear_steer_rad=0.0,
                throttle_pct=0.0,
                brake_pct=100.0,
                reverse=False,
            )
            return
        self.applied_pattern = command.pattern
        state = self.world.state
        throttle_pct, brake_pct, reverse = self.pid.update(command.speed_mps, state.speed_mps, dt_s)
        front_rad, rear_rad = command.front_steer_rad, command.rear_steer_rad
        if pose_loop:
            assert self.pose is not None and self.expected_pose is not None
            front_rad, rear_rad = self.pose_loop.update(
                command.pattern,
                state.speed_mps,
                Pose2D(self.pose.x_m, self.pose.y_m, self.pose.yaw_rad),
                Pose2D(self.expected_pose.x_m, self.expected_pose.y_m, self.expected_pose.yaw_rad),
                state.front_steer_rad,
                -state.rear_steer_rad,
                dt_s,
            )
        else:
            self.pose_loop.reset()
        self.world.set_inputs(
            WORLD_SOURCE,
            pattern=command.pattern,
            front_steer_rad=front_rad,
            rear_steer_rad=-rear_rad,  # the sim counts counter-steer positive
            throttle_pct=throttle_pct,
            brake_pct=brake_pct,
            reverse=reverse,
        )

    # ---- transmitting -----------------------------------------------------------------
    def _condition_frames(self) -> list[OutFrame]:
        f = self.faults
        wanted = (
            BusCondition.BUS_OFF
            if f.bus_off
            else BusCondition.PASSIVE
            if f.error_passive
            else BusCondition.ACTIVE
        )
        if wanted is self._condition:
            return []
        self._condition = wanted
        if not self.emit_error_frames:
            return []
        error_class, data = error_frame(wanted)
        return [OutFrame(error_class, data, is_error_frame=True)]

    def _queue(self, message: Pc104Message, now_s: float) -> None:
        frame_id = protocol.spec_for(type(message)).frame_id
        counter = self._counters[frame_id]
        if not self.faults.stuck_counter:
            self._counters[frame_id] = (counter + 1) % protocol.COUNTER_MODULO
        arbitration_id, data = self._encode(message, counter)
        self.frames_sent += 1
        f = self.faults
        if f.drop_all or (f.drop_one_in > 0 and self.frames_sent % f.drop_one_in == 0):
            return
        if f.bad_crc:
            data = data[:-1] + bytes([data[-1] ^ 0xFF])
        self._delayed.append((now_s + f.delay_s, OutFrame(arbitration_id, data)))

    def _encode(self, message: Pc104Message, counter: int) -> tuple[int, bytes]:
        """`protocol.encode`, remembered per message type while the message stays the same.

        Encoding through cantools costs 20-70 µs a frame, and most reports repeat (all of
        them at a standstill, the wheel angles whenever the steering holds): the same
        message with a counter already seen is the same frame. Every signal is a scaled
        integer, so equal messages (0.0 == -0.0 included) encode to equal bytes; a message
        that does not encode raises as ever and is not remembered.
        """
        last = self._encoded.get(type(message))
        if last is None or last[0] != message:
            last = self._encoded[type(message)] = (message, {})
        frame = last[1].get(counter)
        if frame is None:
            frame = last[1][counter] = protocol.encode(message, counter)
        return frame

    def _build(self, message_type: type, now_s: float) -> Pc104Message:
        state = self.world.state
        if message_type is Pc104Status:
            invalid_recently = now_s - self.last_invalid_s < 1.0
            automatic = self.control_source is ControlSource.AUTOMATIC
            return Pc104Status(
                active_pattern=self.applied_pattern,
                ready=automatic and not self.stop_required,
                control_source=self.control_source,
                platform_leveling=bool(
                    self.command is not None and self.command.level_platform and automatic
                ),
                stop_required=self.stop_required,
                faults=Pc104Faults(
                    command_timeout=automatic and not self.command_fresh(now_s),
                    command_invalid=invalid_recently,
                    pose=self.pose_fault,
                ),
                measured_speed_mps=_clamp(state.speed_mps, _SPEED_LIMIT_MPS),
                bad_command_frames=self.bad_command_frames,
            )
        if message_type is WheelAngles:
            front_rad, rear_rad = state.front_steer_rad, -state.rear_steer_rad
            rows = [front_rad + (rear_rad - front_rad) * i / 3 for i in range(4)]
            r = [_clamp(a, _ROW_LIMIT_RAD) for a in rows]
            return WheelAngles((r[0], r[1], r[2], r[3]))
        if message_type is MotorPulses:
            counts = int(state.odometer_m * self.params.pulses_per_m) % PULSE_COUNTER_MODULO
            return MotorPulses(counts, counts, counts, counts)
        if message_type is Inclinometer:
            noise = self.params.inclinometer_noise_rad
            pitch, roll = (_clamp(self._rng.gauss(0.0, noise), _TILT_LIMIT_RAD) for _ in "pr")
            return Inclinometer(pitch, roll)
        uptime_s = int(max(now_s - self.boot_s, 0.0)) % 65536
        return Pc104Heartbeat(Pc104State.RUNNING, uptime_s)


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


_TRANSMITTED: tuple[type, ...] = (
    Pc104Status,
    WheelAngles,
    MotorPulses,
    Inclinometer,
    Pc104Heartbeat,
)
__all__ = [
    "OutFrame",
    "Pc104TwinCore",
    "PidGains",
    "PidSpeedController",
    "TwinFaults",
    "TwinParams",
]
