"""What each actuator path is told, once the mode machine has decided the cycle's mode.

The core decides *whether* the vehicle is under automatic control; this decides *what*
that means for each path: the autopilot's steering wish through arbitration and the
command limiter, the set speed through the speed ramp (a controlled stop under
hold-to-move), the safe-state brake, the panel's lamps and text, and the PC104's motion
command. Holding the limiter and the ramps here, behind ``reset()``/``update()``, keeps the
rate limits' memory in one place that a restart clears.

Speed goes one of two ways (``speed_path``). ``pc104``: the ramped set speed is the
PC104's set-point and our throttle board stays released. ``pedals`` (a vehicle without a
PC104, Stanley et al.'s Husky): in SPEED_HOLD the ramped set speed is the target of the
throttle/brake controller (:mod:`appliance.guidance.pedal_speed`), whose pedal positions
pass arbitration and the throttle/brake limits before they reach the boards; in ENGAGED
the speed is the operator's foot and both our pedals are released; in a safe mode the
throttle is released and the safe-state brake applies, never less than the brake we were
already pulling. The pedals have a limiter of their own, so a broken steering wish (a
non-finite angle resets the steering limiter) cannot also throw the brake on, and the
controller is reset whenever the pedals are not ours: it never integrates or plans over
cycles it did not command.
"""

from __future__ import annotations

import math
from typing import TypeVar

from appliance.config import parts
from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig
from appliance.core.autopilot import AutopilotWish
from appliance.core.observe import Measurements
from appliance.core.output import SAFE_MODES, CoreOutput, Note, hl_state, printable
from appliance.guidance.pedal_speed import PedalCommand, PedalSpeedController
from appliance.modes import AUTOMATIC_MODES, Mode, ModeState
from drivers.actuators.messages import (
    BrakeCommand,
    Lamps,
    PanelCommand,
    SteeringCommand,
    SteeringMode,
    ThrottleCommand,
)
from drivers.geometry import Pose2D
from drivers.pc104 import protocol
from drivers.pc104.messages import (
    HlExpectedPose,
    HlPose,
    MotionCommand,
    MotionPattern,
    PoseState,
    SteeringLoop,
)
from safety.arbitration import RELEASED, OperatorInput, arbitrate
from safety.limits import ActuatorCommand, CommandLimiter
from safety.safe_state import SafeBrake, SafeKind, SpeedRamp

MAX_DISPLAY = 32


class CommandPaths:
    """The cycle's command for every actuator path, from the mode, the operator and the wish."""

    def __init__(
        self,
        config: VehicleConfig,
        calibration: Calibration | None,
        pattern: MotionPattern,
        max_speed_mps: float,
    ) -> None:
        self.calibration = calibration
        self.pattern = pattern
        self.max_steer_rad = math.radians(config.limits.max_steer_angle_deg)
        # Never aimed past what the calibration's pot map covers (inside the steering's
        # lock): a servo held against its lock reports a position error, and a tyre angle
        # the pot cannot read back is not one the safety rules can check.
        self.steer_range_rad = (
            (-math.inf, math.inf) if calibration is None else calibration.valid_tyre_range_rad
        )
        self.max_speed_mps = max_speed_mps
        self.hold_to_move = config.engagement.hold_to_move
        self.steering_loop = SteeringLoop(config.docking.pose_loop)
        self.limiter = CommandLimiter(parts.limit_params(config.limits))
        self.brake = SafeBrake(parts.safe_brake_params(config.safety, config.limits))
        self.speed = SpeedRamp(parts.speed_ramp_params(config.engagement, config.limits))
        self.pedals: PedalSpeedController | None = (
            PedalSpeedController(
                parts.pedal_speed_params(config), parts.pedal_plant(config, calibration)
            )
            if config.speed_path == "pedals"
            else None
        )
        self.pedal_limiter = CommandLimiter(parts.limit_params(config.limits))
        self.reset()

    def reset(self) -> None:
        self.limiter.reset()
        self.brake.reset()
        self.speed.reset()
        self.pedal_limiter.reset()
        if self.pedals is not None:
            self.pedals.reset()
        # The steering command last sent (None: released); the override and tracking rules
        # compare the measured angle with it.
        self.last_steer_rad: float | None = None
        # The brake our speed controller last applied: a safe state never brakes less.
        self.brake_floor_pct = 0.0
        # The speed controller's last output (None: the pedals were not ours), for status.
        self.last_pedal: PedalCommand | None = None

    def engaged(self) -> None:
        """Automatic control begins: no rate limit or controller remembers a command from
        before."""
        self.limiter.reset()
        self.pedal_limiter.reset()
        if self.pedals is not None:
            self.pedals.reset()

    def speed_hold_entered(self) -> None:
        """Speed hold begins: the ramp starts from the set-point it has reached (on the
        pedals path, the measured speed the set speed was locked at), the controller
        from released pedals."""
        self.speed.reset(self.speed.setpoint_mps)
        if self.pedals is not None:
            self.pedals.reset()

    def update(
        self,
        state: ModeState,
        operator: OperatorInput,
        m: Measurements,
        wish: AutopilotWish,
        notes: tuple[Note, ...],
        now_s: float,
    ) -> CoreOutput:
        mode = state.mode
        automatic = mode in AUTOMATIC_MODES
        safe = mode in SAFE_MODES
        request = ActuatorCommand(wish.steer_tyre_rad if automatic else None, 0.0, 0.0)
        chosen = arbitrate(operator, safe, request if automatic else None, automatic, False)
        steer_request = None if chosen is None else chosen.steer_angle_rad
        if steer_request is not None and math.isfinite(steer_request):
            low, high = self.steer_range_rad
            steer_request = min(max(steer_request, low), high)
        limited, violations = self.limiter.update(
            ActuatorCommand(steer_request, 0.0, 0.0),
            m.speed_mps if m.speed_mps is not None else 0.0,
            now_s,
            m.steer_tyre_rad,
        )
        steer_rad = limited.steer_angle_rad if automatic else None
        if "input_not_finite" in violations:
            steer_rad = None
        self.last_steer_rad = steer_rad

        speed_setpoint: float | None = None
        stopping = self.hold_to_move and not state.hold_to_move_held
        # On the pedals path ENGAGED's speed is the operator's foot: nothing is set, and
        # the ramp follows the measured speed, which a + press then locks.
        operators_speed = self.pedals is not None and mode is Mode.ENGAGED
        if automatic and not operators_speed:
            target = self._speed_target(state, operator, m, wish)
            speed_setpoint = self.speed.update(target, now_s, controlled_stop=stopping)
        else:
            self.speed.reset(m.speed_mps if m.speed_mps is not None else 0.0)

        kind = SafeKind.ESTOP if mode is Mode.ESTOP else SafeKind.FAULT if safe else SafeKind.NONE
        safe_brake_pct = self.brake.update(kind, now_s)
        throttle, brake = self._pedal_commands(
            state, operator, m, wish, speed_setpoint, stopping, safe_brake_pct, now_s
        )
        return CoreOutput(
            now_s=now_s,
            mode=mode,
            steering=self._steering_command(steer_rad, m),
            throttle=throttle,
            brake=brake,
            panel=panel_command(state),
            pc104=self._pc104_command(steer_rad, speed_setpoint, wish),
            hl_state=hl_state(mode),
            operator=operator,
            steer_tyre_rad=steer_rad,
            speed_setpoint_mps=speed_setpoint,
            notes=notes,
            pc104_pose=_pose_frame(wish.pose, wish.pose_state),
            pc104_expected_pose=_expected_frame(wish.expected_pose, self.steering_loop)
            if automatic
            else None,
        )

    def _pedal_commands(
        self,
        state: ModeState,
        operator: OperatorInput,
        m: Measurements,
        wish: AutopilotWish,
        speed_setpoint: float | None,
        stopping: bool,
        safe_brake_pct: float,
        now_s: float,
    ) -> tuple[ThrottleCommand, BrakeCommand]:
        """The throttle and brake boards' commands (see the module for each mode)."""
        mode = state.mode
        safe = mode in SAFE_MODES
        controller = self.pedals
        foot = operator.brake_pedal or operator.throttle_pedal
        ours = (
            controller is not None
            and mode is Mode.SPEED_HOLD
            and speed_setpoint is not None
            and not foot
        )
        request = None
        pedal: PedalCommand | None = None
        if ours and controller is not None and speed_setpoint is not None:
            # Deny by default: an unknown speed makes the controller brake (its FAULT), and
            # a stop wish or a reverse one (this path drives forward only) stops.
            stop = stopping or wish.reverse or wish.pattern is MotionPattern.STOP
            if wish.pedals_pct is not None and not stop:
                # A source that drives the pedals itself (the pedal sweep): its levels,
                # through the same arbitration and limits; the controller starts afresh
                # when it has the pedals again.
                controller.reset()
                request = ActuatorCommand(None, *wish.pedals_pct)
            else:
                measured = m.speed_mps if m.speed_mps is not None else math.nan
                pedal = controller.update(
                    speed_setpoint, measured, None, now_s, stop_requested=stop
                )
                request = ActuatorCommand(None, pedal.throttle_pct, pedal.brake_pct)
        elif controller is not None:
            controller.reset()  # not ours this cycle: start afresh when it is again
        chosen = arbitrate(operator, False, request, False, ours) or RELEASED
        # Every cycle, so the throttle's rate limit remembers what really went out (0 when
        # released): taking over again ramps from there.
        limited, violations = self.pedal_limiter.update(
            ActuatorCommand(None, chosen.throttle_pct, chosen.brake_pct),
            m.speed_mps if m.speed_mps is not None else 0.0,
            now_s,
        )
        self.last_pedal = pedal
        if safe:
            brake_pct = max(safe_brake_pct, self.brake_floor_pct)
            return ThrottleCommand(enable=False), BrakeCommand(enable=True, position_pct=brake_pct)
        if not ours:
            self.brake_floor_pct = 0.0
            return ThrottleCommand(enable=False), BrakeCommand(enable=False)
        throttle_pct, brake_pct = limited.throttle_pct, limited.brake_pct
        if "input_not_finite" in violations and controller is not None:
            controller.reset()  # the limiter sent its safe command: brake, throttle shut
        if brake_pct > 0.0:
            throttle_pct = 0.0  # never both pedals: the brake wins
        self.brake_floor_pct = brake_pct
        return (
            ThrottleCommand(enable=True, position_pct=throttle_pct),
            BrakeCommand(enable=True, position_pct=brake_pct),
        )

    def _speed_target(
        self, state: ModeState, operator: OperatorInput, m: Measurements, wish: AutopilotWish
    ) -> float:
        cap = self.max_speed_mps
        if wish.max_speed_mps is not None:
            cap = min(cap, wish.max_speed_mps)
        if state.mode is Mode.SPEED_HOLD and wish.speed_mps is not None:
            # A source's own speed (a NaN or a negative one stands: deny by default).
            wanted = wish.speed_mps if math.isfinite(wish.speed_mps) else 0.0
            return min(max(0.0, wanted), cap)
        if state.mode is Mode.SPEED_HOLD and state.set_speed_mps is not None:
            return min(state.set_speed_mps, cap)
        # ENGAGED: speed is the operator's; their throttle pedal is forwarded to the PC104.
        if operator.brake_pedal or m.throttle_pedal_pct is None:
            return 0.0
        return min(cap, cap * max(0.0, m.throttle_pedal_pct) / 100.0)

    def _steering_command(self, steer_rad: float | None, m: Measurements) -> SteeringCommand:
        calibration = self.calibration
        if (
            steer_rad is None
            or calibration is None
            or m.servo_position_rad is None
            or m.steer_wheel_rad is None
        ):
            return SteeringCommand(SteeringMode.RELEASE)
        # The servo's encoder is relative: aim it by the remaining error the pot sees.
        target_wheel_rad = calibration.wheel_rad_from_tyre(steer_rad)
        setpoint = m.servo_position_rad + (target_wheel_rad - m.steer_wheel_rad)
        return SteeringCommand(SteeringMode.POSITION, wheel_angle_setpoint_rad=setpoint)

    def _pc104_command(
        self, steer_rad: float | None, speed_mps: float | None, wish: AutopilotWish
    ) -> MotionCommand:
        if speed_mps is None or steer_rad is None:
            return MotionCommand.stop()
        # The rear row's angle only in REAR_STEER, and never past the steering's lock.
        limit = self.max_steer_rad
        rear = max(-limit, min(limit, wish.rear_steer_rad))
        pattern = wish.pattern or self.pattern
        return MotionCommand(
            pattern=pattern,
            speed_mps=-speed_mps if wish.reverse else speed_mps,
            front_steer_rad=steer_rad,
            rear_steer_rad=rear if pattern is MotionPattern.REAR_STEER else 0.0,
        )


_Frame = TypeVar("_Frame", HlPose, HlExpectedPose)


def _carried(message: _Frame) -> _Frame | None:
    """``message``, or None when its frame cannot carry it (a pose beyond ±32 m of the
    site's origin): a PC104 steering on pose then stops for the missing frame, as it
    must, and the control loop does not fail over a report."""
    try:
        protocol.encode(message, 0)
    except protocol.CommandRefused:
        return None
    return message


def _pose_frame(pose: Pose2D | None, state: PoseState) -> HlPose | None:
    if pose is None:
        return None
    return _carried(HlPose(pose.x_m, pose.y_m, math.remainder(pose.yaw_rad, math.tau), state))


def _expected_frame(pose: Pose2D | None, loop: SteeringLoop) -> HlExpectedPose | None:
    if pose is None:
        return None
    yaw_rad = math.remainder(pose.yaw_rad, math.tau)
    return _carried(HlExpectedPose(pose.x_m, pose.y_m, yaw_rad, loop))


def panel_command(state: ModeState) -> PanelCommand:
    """The panel's lamps and its 32-character text for the mode."""
    mode = state.mode
    lamps = Lamps.NONE
    if mode in (Mode.ERROR, Mode.ESTOP):
        lamps |= Lamps.OVERRIDE | Lamps.WARNING
    if mode in AUTOMATIC_MODES:
        lamps |= Lamps.ENGAGED
    match mode:
        case Mode.SPEED_HOLD:
            text = f"SPEED HOLD {state.set_speed_mps or 0.0:.2f} m/s"
        case Mode.ERROR:
            first = state.faults[0].reason if state.faults else "cleared: press OVERRIDE"
            text = f"ERROR {first}"
        case Mode.ESTOP:
            text = "E-STOP: release, then OVERRIDE"
        case _:
            text = str(mode).upper().replace("_", " ")
    return PanelCommand(lamps, printable(text)[:MAX_DISPLAY])
