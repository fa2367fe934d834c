"""A bench vehicle for the control core: plain state in, ``ControlInputs`` out, fake time.

It closes the loop the core expects, just enough to mean something: the steering wheel
follows the core's POSITION set-point (servo frame) at a rate limit unless the operator
holds it or the servo lost its torque; the pot reads the wheel through the calibration;
the PC104's measured speed follows its speed set-point with a first-order lag and STOP
decelerates it to 0; the brake actuator follows the brake command. Tests change the
operator's hands, feet and buttons and the health of every input, then ``step``.
Deterministic: no clock, no randomness.
"""

from __future__ import annotations

import math

from appliance.config.calibration import Calibration
from appliance.config.simulated_calibration import simulated_calibration
from appliance.core.core import ControlCore
from appliance.core.inputs import ControlInputs, LinkCounts, TabletHold
from appliance.core.output import CoreOutput
from drivers.actuators.messages import (
    BUTTON_ORDER,
    BoardStatus,
    BrakeTelemetry,
    Buttons,
    FaultCode,
    PanelTelemetry,
    SteeringMode,
    SteeringTelemetry,
    ThrottleTelemetry,
)
from drivers.pc104.messages import ControlSource, MotionPattern, Pc104Faults, Pc104Status

SIM_CALIBRATION = Calibration.from_file(simulated_calibration("sim"))

FRESH_AGE_S = 0.005
SERVO_OFFSET_RAD = 0.7  # the servo encoder is relative: its zero is not straight ahead
WHEEL_RATE_RAD_PER_S = 12.0  # faster than the limiter lets the command move
HOLD_TORQUE_NM = 15.0  # the servo pushing against the operator's hands
IDLE_TORQUE_NM = 1.0
SPEED_LAG_S = 0.1  # the PC104's speed loop, first order
STOP_DECEL_MPS2 = 2.0  # the PC104 braking on STOP
BOARDS = ("steering", "throttle", "brake", "panel")
# Inputs that travel together: the pot is in the steering board's telemetry.
ALIASES = {"board.steering": ("board.steering", "steering.pot")}


class BenchVehicle:
    def __init__(self, calibration: Calibration | None = None, now_s: float = 0.0) -> None:
        self.calibration = calibration or SIM_CALIBRATION
        self.now_s = now_s
        low, high = self.calibration.valid_wheel_range_rad
        self._wheel_range_rad = (low + 1e-6, high - 1e-6)
        self.wheel_rad = 0.0
        self.held_wheel_rad: float | None = None
        self.torque_loss = False  # the servo turns but the wheel no longer follows it
        self.pot_counts: int | None = None  # a broken pot's reading instead of the wheel's
        self.brake_foot_pct = 0.0
        self.throttle_foot_pct = 0.0
        self.brake_actuator_pct = 0.0
        self.throttle_actuator_pct = 0.0
        self.press_counts = [0, 0, 0, 0, 0]
        self.buttons_down = Buttons.NONE
        self.panel_seq = 0
        self.speed_mps = 0.0
        self.distance_m = 0.0
        self.pc104_source = ControlSource.AUTOMATIC
        self.pc104_ready = True
        self.pc104_faults = Pc104Faults()
        self.link_errors = 0
        self.link_good = 0
        self.stale: set[str] = set()
        self.unplugged: set[str] = set()
        self.board_faults: dict[str, FaultCode] = {}
        self.last: CoreOutput | None = None
        self.tablet: TabletHold | None = None  # the tablet page's hold, where one is paired

    # ---- what tests do to the vehicle -------------------------------------------------
    def press(self, button: Buttons) -> None:
        index = BUTTON_ORDER.index(button)
        self.press_counts[index] = (self.press_counts[index] + 1) % 256

    def hold_button(self, button: Buttons, down: bool) -> None:
        """Hold a button down (hold-to-move, the mushroom); pushing it counts as a press."""
        if down and not self.buttons_down & button:
            self.press(button)
        self.buttons_down = self.buttons_down | button if down else self.buttons_down & ~button

    def estop(self, down: bool) -> None:
        self.hold_button(Buttons.ESTOP, down)

    def hold_wheel(self, tyre_rad: float) -> None:
        """The operator's hands put the wheels at ``tyre_rad`` and keep them there."""
        wheel_rad = self._clamp_wheel(tyre_rad * self.calibration.steering_ratio)
        self.held_wheel_rad = self.wheel_rad = wheel_rad

    def _clamp_wheel(self, wheel_rad: float) -> float:
        low, high = self._wheel_range_rad
        return min(max(wheel_rad, low), high)

    def let_go(self) -> None:
        self.held_wheel_rad = None

    def brake_pedal(self, pct: float) -> None:
        self.brake_foot_pct = pct

    def throttle_pedal(self, pct: float) -> None:
        self.throttle_foot_pct = pct

    def make_stale(self, name: str) -> None:
        self.stale.update(ALIASES.get(name, (name,)))

    def unplug(self, name: str) -> None:
        self.unplugged.update(ALIASES.get(name, (name,)))

    def make_fresh(self, name: str) -> None:
        """Fresh and plugged in again."""
        for alias in ALIASES.get(name, (name,)):
            self.stale.discard(alias)
            self.unplugged.discard(alias)

    def board_fault(self, board: str, code: FaultCode) -> None:
        assert board in BOARDS, board
        self.board_faults[board] = code

    def bump_link_errors(self, errors: int) -> None:
        self.link_errors += errors

    # ---- what the core sees ------------------------------------------------------------
    @property
    def tyre_rad(self) -> float:
        return self.wheel_rad / self.calibration.steering_ratio

    @property
    def pot_tyre_rad(self) -> float | None:
        """What the pot says (quantised to counts), as the core converts it."""
        return self.calibration.tyre_rad_from_counts(self._pot_counts())

    @property
    def torque_nm(self) -> float:
        if self.held_wheel_rad is not None:
            return HOLD_TORQUE_NM
        return 0.2 if self.torque_loss else IDLE_TORQUE_NM

    def _pot_counts(self) -> int:
        if self.pot_counts is not None:
            return self.pot_counts
        return round(self.calibration.counts_from_wheel_rad(self.wheel_rad))

    def _status(self, board: str) -> tuple[BoardStatus, FaultCode]:
        fault = self.board_faults.get(board, FaultCode.NONE)
        return (BoardStatus.NONE if fault is FaultCode.NONE else BoardStatus.FAULT), fault

    def inputs(self, age_limits_s: dict[str, float] | None = None) -> ControlInputs:
        limits = age_limits_s or {}
        ages = {name: FRESH_AGE_S for name in limits}
        for name in self.stale:
            ages[name] = 2.0 * limits.get(name, 1.0)
        for name in self.unplugged:
            ages[name] = math.inf
        steering = throttle = brake = panel = status = None
        if "board.steering" not in self.unplugged:
            steering = SteeringTelemetry(
                *self._status("steering"),
                command_seq_echo=0,
                servo_position_rad=self.wheel_rad + SERVO_OFFSET_RAD,
                motor_current_a=self.torque_nm / 1.5,
                motor_torque_nm=self.torque_nm,
                pot_raw_counts=self._pot_counts(),
                supply_voltage_v=24.0,
            )
        if "board.throttle" not in self.unplugged:
            throttle = ThrottleTelemetry(
                *self._status("throttle"),
                command_seq_echo=0,
                actuator_position_pct=self.throttle_actuator_pct,
                pedal_position_pct=max(self.throttle_actuator_pct, self.throttle_foot_pct),
            )
        if "board.brake" not in self.unplugged:
            brake = BrakeTelemetry(
                *self._status("brake"),
                command_seq_echo=0,
                actuator_position_pct=self.brake_actuator_pct,
                pedal_position_pct=max(self.brake_actuator_pct, self.brake_foot_pct),
            )
        if "board.panel" not in self.unplugged:
            c0, c1, c2, c3, c4 = self.press_counts
            panel = PanelTelemetry(
                *self._status("panel"), 0, self.buttons_down, (c0, c1, c2, c3, c4)
            )
        if "pc104.status" not in self.unplugged:
            pattern = MotionPattern.STOP if self.last is None else self.last.pc104.pattern
            status = Pc104Status(
                active_pattern=pattern,
                ready=self.pc104_ready,
                control_source=self.pc104_source,
                faults=self.pc104_faults,
                measured_speed_mps=self.speed_mps,
            )
        return ControlInputs(
            ages_s=ages,
            steering=steering,
            throttle=throttle,
            brake=brake,
            panel=panel,
            panel_seq=None if panel is None else self.panel_seq,
            pc104_status=status,
            pc104_link=LinkCounts(errors=self.link_errors, good=self.link_good),
            tablet=self.tablet,
        )

    # ---- the loop ------------------------------------------------------------------------
    def advance(self, dt_s: float) -> None:
        """Physics over ``dt_s`` under the last commands."""
        last = self.last
        if self.held_wheel_rad is not None:
            self.wheel_rad = self.held_wheel_rad
        elif last is not None and last.steering.mode is SteeringMode.POSITION:
            target = last.steering.wheel_angle_setpoint_rad - SERVO_OFFSET_RAD
            step = 0.0 if self.torque_loss else WHEEL_RATE_RAD_PER_S * dt_s
            self.wheel_rad = self._clamp_wheel(
                self.wheel_rad + min(max(target - self.wheel_rad, -step), step)
            )
        self.brake_actuator_pct = last.brake.position_pct if last and last.brake.enable else 0.0
        self.throttle_actuator_pct = (
            last.throttle.position_pct if last and last.throttle.enable else 0.0
        )
        before = self.speed_mps
        if self.pc104_source is ControlSource.AUTOMATIC:
            if last is None or last.pc104.pattern is MotionPattern.STOP:
                self.speed_mps = max(0.0, self.speed_mps - STOP_DECEL_MPS2 * dt_s)
            else:
                alpha = 1.0 - math.exp(-dt_s / SPEED_LAG_S)
                self.speed_mps += (last.pc104.speed_mps - self.speed_mps) * alpha
        self.distance_m += 0.5 * (before + self.speed_mps) * dt_s
        self.now_s += dt_s
        self.panel_seq += 1
        self.link_good += 1

    def step(self, core: ControlCore, dt_s: float = 0.01) -> CoreOutput:
        self.advance(dt_s)
        self.last = core.step(self.inputs(dict(core.staleness.age_limits_s)), self.now_s)
        return self.last

    def run(self, core: ControlCore, duration_s: float, dt_s: float = 0.01) -> list[CoreOutput]:
        return [self.step(core, dt_s) for _ in range(round(duration_s / dt_s))]
