"""The four simulated boards and the set the daemon starts for ``sim://`` ports.

Each twin owns the physics of its board and writes what the board does to the vehicle into
its own slot of the shared :class:`SimWorld` ("steering_servo", "throttle_board",
"brake_board"); the operator's hands and feet go to the world's "operator" slot. The true
parameters (servo limits, pot mapping, safe brake level) are attributes, so tests and the
calibration work can compare what the host estimates with what is really there.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from typing import ClassVar

from appliance.sim.linkage import SteeringLinkage
from appliance.sim.world import SimWorld
from drivers.actuators.messages import (
    BUTTON_ORDER,
    BoardKind,
    BoardStatus,
    BrakeCommand,
    BrakeTelemetry,
    Buttons,
    FaultCode,
    Lamps,
    PanelCommand,
    PanelTelemetry,
    SteeringCommand,
    SteeringMode,
    SteeringTelemetry,
    ThrottleCommand,
    ThrottleTelemetry,
)
from drivers.actuators.steering_model import (
    PotMapping,
    ServoParams,
    ServoState,
    ServoTarget,
    available_torque_nm,
    pot_counts,
    step_servo,
)
from drivers.actuators.twin import BoardTwin

POSITION_ERROR_RAD = 0.2
POSITION_ERROR_AFTER_S = 0.5
FOLLOWING_SHARE = 0.5  # moving slower than this share of the loop's rate: not following
OVERRIDE_MARGIN_PCT = 5.0
HOST_LOST_TEXT = "HOST LOST"


class SteeringTwin(BoardTwin[SteeringCommand]):
    """Servo on the column plus the absolute pot, read by the same board."""

    board = BoardKind.STEERING
    command_type = SteeringCommand

    def __init__(
        self,
        link_path: str,
        world: SimWorld | None = None,
        *,
        params: ServoParams | None = None,
        pot_mapping: PotMapping | None = None,
        encoder_offset_rad: float = 0.0,
        linkage_cubic: float = 0.0,
        seed: int = 0,
        **board: float,
    ) -> None:
        super().__init__(link_path, **board)
        self.world = world
        self.params = params if params is not None else ServoParams()
        self.linkage = SteeringLinkage(
            self.params.steering_ratio, self.params.wheel_limit_rad, linkage_cubic
        )
        self.pot_mapping = pot_mapping if pot_mapping is not None else PotMapping()
        # The servo encoder is relative: zero where the servo was mounted, not straight ahead.
        self.encoder_offset_rad = encoder_offset_rad
        self.servo = ServoState(motor_rad=encoder_offset_rad)
        self.torque_scale = 1.0
        self._rng = random.Random(seed)
        self._position_error_s = 0.0
        self._hands_wheel_rad: float | None = None  # the operator holding the wheel here

    @property
    def wheel_angle_rad(self) -> float:
        return self.servo.wheel_rad

    def operator_hands(self, wheel_rad: float | None) -> None:
        """The operator grips the steering wheel at ``wheel_rad`` (None: lets go).

        A person is stronger than the servo: the wheel goes where they hold it, and a servo
        in position mode stalls against them at its torque limit, which is what the host's
        override rule sees (pot far from the command, servo torque high). Nobody turns
        it past its lock, however hard they try.
        """
        if wheel_rad is not None:
            lock = self.params.wheel_limit_rad
            wheel_rad = max(-lock, min(lock, wheel_rad))
        self._hands_wheel_rad = wheel_rad

    def inject_torque_loss(self, torque_scale: float = 0.0) -> None:
        """Supply sag or a failed motor: the servo gives only this fraction of its torque."""
        self.torque_scale = torque_scale

    def is_release(self, command: SteeringCommand) -> bool:
        return command.mode is SteeringMode.RELEASE

    def is_engaging(self, command: SteeringCommand) -> bool:
        return command.mode is not SteeringMode.RELEASE

    def _target(self) -> ServoTarget:
        command = self.command
        if command is None:
            return ServoTarget(SteeringMode.RELEASE)
        return ServoTarget(
            command.mode,
            command.wheel_angle_setpoint_rad + self.encoder_offset_rad,
            command.torque_setpoint_nm,
        )

    def _update(self, now_s: float, dt_s: float) -> None:
        target = self._target()
        before_rad = self.servo.motor_rad
        self.servo = step_servo(self.servo, target, dt_s, self.params, self.torque_scale)
        hands = self._hands_wheel_rad
        if hands is not None:
            half_play = self.params.backlash_rad / 2.0
            motor = min(max(self.servo.motor_rad, hands - half_play), hands + half_play)
            push = 0.0
            error = target.motor_setpoint_rad - motor
            if target.mode is SteeringMode.POSITION and abs(error) > self.params.deadband_rad:
                push = available_torque_nm(error, self.params, self.torque_scale)
                push = push if error > 0 else -push
            self.servo = ServoState(motor_rad=motor, wheel_rad=hands, torque_nm=push)
        error = abs(target.motor_setpoint_rad - self.servo.motor_rad)
        # A following error, as a servo drive judges it: far from the setpoint *and* not
        # getting there at the rate its position loop asks for (held, stalled, at the
        # lock). Far alone is a servo slewing after a large step, which is no fault.
        asked_rad_per_s = min(
            self.params.position_gain_per_s * error, self.params.max_rate_rad_per_s
        )
        moved_rad_per_s = abs(self.servo.motor_rad - before_rad) / dt_s if dt_s > 0.0 else 0.0
        stuck = moved_rad_per_s < FOLLOWING_SHARE * asked_rad_per_s
        if target.mode is SteeringMode.POSITION and error > POSITION_ERROR_RAD and stuck:
            self._position_error_s += dt_s
        else:
            self._position_error_s = 0.0
        if self.world is not None:
            tyre_rad = self.linkage.tyre_rad(self.servo.wheel_rad)
            self.world.set_inputs("steering_servo", front_steer_rad=tyre_rad)

    def hardware_fault(self) -> FaultCode:
        if self._position_error_s > POSITION_ERROR_AFTER_S:
            return FaultCode.POSITION_ERROR
        if self.torque_scale < 0.7:
            return FaultCode.SUPPLY_UNDERVOLTAGE
        return FaultCode.NONE

    def telemetry(self, status: BoardStatus, fault: FaultCode, echo: int) -> SteeringTelemetry:
        noise = self._rng.gauss(0.0, self.pot_mapping.noise_counts)
        torque = max(-32.0, min(32.0, self.servo.torque_nm))
        return SteeringTelemetry(
            status=status,
            fault=fault,
            command_seq_echo=echo,
            servo_position_rad=self.servo.motor_rad - self.encoder_offset_rad,
            motor_current_a=max(-32.0, min(32.0, torque / self.params.torque_constant_nm_per_a)),
            motor_torque_nm=torque,
            pot_raw_counts=pot_counts(self.servo.wheel_rad, self.pot_mapping, noise),
            supply_voltage_v=max(0.0, self.params.nominal_supply_v * self.torque_scale),
        )


def _clip_pct(value: float) -> float:
    return max(0.0, min(100.0, value))


def approach_pct(
    value_pct: float, target_pct: float, dt_s: float, tau_s: float, rate_pct_per_s: float
) -> float:
    """First-order lag with a rate limit: a cable actuator pulling its pedal."""
    if dt_s <= 0.0:
        return value_pct
    alpha = dt_s / (tau_s + dt_s)
    step = (target_pct - value_pct) * alpha
    limit = rate_pct_per_s * dt_s
    return value_pct + max(-limit, min(limit, step))


PedalCommand = ThrottleCommand | BrakeCommand


class _PedalTwin(BoardTwin[PedalCommand]):
    """Shared by throttle and brake: an actuator with lag, and the pedal it pulls."""

    world_source: ClassVar[str]
    world_field: ClassVar[str]

    def __init__(
        self,
        link_path: str,
        world: SimWorld | None = None,
        *,
        time_constant_s: float = 0.08,
        max_rate_pct_per_s: float = 250.0,
        **board: float,
    ) -> None:
        super().__init__(link_path, **board)
        self.world = world
        self.time_constant_s = time_constant_s
        self.max_rate_pct_per_s = max_rate_pct_per_s
        self.actuator_position_pct = 0.0
        self.operator_pedal_pct = 0.0  # the operator's foot

    def is_release(self, command: PedalCommand) -> bool:
        return not command.enable

    def is_engaging(self, command: PedalCommand) -> bool:
        return command.enable

    def safe_default_pct(self) -> float:
        return 0.0

    def target_pct(self) -> float:
        command = self.command
        if command is None:
            return self.safe_default_pct()
        return command.position_pct if command.enable else 0.0

    @property
    def pedal_position_pct(self) -> float:
        return max(self.actuator_position_pct, self.operator_pedal_pct)

    def operator_override(self) -> bool:
        return self.operator_pedal_pct > self.actuator_position_pct + OVERRIDE_MARGIN_PCT

    def _update(self, now_s: float, dt_s: float) -> None:
        self.actuator_position_pct = approach_pct(
            self.actuator_position_pct,
            self.target_pct(),
            dt_s,
            self.time_constant_s,
            self.max_rate_pct_per_s,
        )
        if self.world is not None:
            self.world.set_inputs(
                self.world_source, **{self.world_field: self.actuator_position_pct}
            )

    def _pedal_fields(self) -> tuple[float, float]:
        return _clip_pct(self.actuator_position_pct), _clip_pct(self.pedal_position_pct)


class ThrottleTwin(_PedalTwin):
    board = BoardKind.THROTTLE
    command_type = ThrottleCommand
    world_source = "throttle_board"
    world_field = "throttle_pct"

    # On a vehicle without a PC104 (the Husky) the pedal and the actuator pull the same
    # engine linkage, so the engine feels the larger of the two; with a PC104 the pedal is
    # an input the drive controller reads (the core forwards it), not a linkage.
    pedal_drives_engine = False

    def operator_pedal(self, pct: float) -> None:
        """The operator's foot on the throttle pedal (0: foot off)."""
        self.operator_pedal_pct = _clip_pct(pct)
        if self.world is not None and self.pedal_drives_engine:
            self.world.set_inputs("operator", throttle_pct=self.operator_pedal_pct)

    def telemetry(self, status: BoardStatus, fault: FaultCode, echo: int) -> ThrottleTelemetry:
        actuator, pedal = self._pedal_fields()
        return ThrottleTelemetry(status, fault, echo, round(actuator, 2), round(pedal, 2))


class BrakeTwin(_PedalTwin):
    board = BoardKind.BRAKE
    command_type = BrakeCommand
    world_source = "brake_board"
    world_field = "brake_pct"

    def __init__(
        self,
        link_path: str,
        world: SimWorld | None = None,
        *,
        timeout_brake_pct: float = 50.0,
        estop_brake_pct: float = 100.0,
        **kwargs: float,
    ) -> None:
        super().__init__(link_path, world, **kwargs)
        self.timeout_brake_pct = timeout_brake_pct
        self.estop_brake_pct = estop_brake_pct
        self._tap: tuple[float, float] | None = None  # (pct, duration) waiting for a step
        self._tap_end_s: float | None = None

    def safe_default_pct(self) -> float:
        return self.estop_brake_pct if self.estop_active else self.timeout_brake_pct

    def operator_pedal(self, pct: float) -> None:
        """The operator's foot rests on the brake pedal at ``pct`` until changed (0: off)."""
        self._tap = None
        self._tap_end_s = None
        self.operator_pedal_pct = _clip_pct(pct)
        if self.world is not None:
            self.world.set_inputs("operator", brake_pct=self.operator_pedal_pct)

    def operator_brake_tap(self, pct: float, duration_s: float) -> None:
        """The operator presses the pedal to ``pct`` for ``duration_s`` from the next step."""
        self._tap = (pct, duration_s)

    def _update(self, now_s: float, dt_s: float) -> None:
        if self._tap is not None:
            pct, duration_s = self._tap
            self._tap = None
            self._tap_end_s = now_s + duration_s
            self.operator_pedal_pct = pct
            if self.world is not None:
                self.world.set_inputs("operator", brake_pct=pct)
        elif self._tap_end_s is not None and now_s >= self._tap_end_s:
            self._tap_end_s = None
            self.operator_pedal_pct = 0.0
            if self.world is not None:
                self.world.set_inputs("operator", brake_pct=0.0)
        super()._update(now_s, dt_s)

    def telemetry(self, status: BoardStatus, fault: FaultCode, echo: int) -> BrakeTelemetry:
        actuator, pedal = self._pedal_fields()
        return BrakeTelemetry(status, fault, echo, round(actuator, 2), round(pedal, 2))


def _button(name: str | Buttons) -> Buttons:
    if isinstance(name, Buttons):
        return name
    try:
        return Buttons[name.upper()]
    except KeyError:
        known = [b.name for b in BUTTON_ORDER if b.name is not None]
        raise ValueError(f"unknown button {name!r}; one of {known}") from None


class PanelTwin(BoardTwin[PanelCommand]):
    """Buttons a test can press and hold, lamps it can read back."""

    board = BoardKind.PANEL
    command_type = PanelCommand
    latches = False

    def __init__(
        self, link_path: str, *, on_estop: Callable[[bool], None] | None = None, **board: float
    ) -> None:
        super().__init__(link_path, **board)
        self.on_estop = on_estop  # the hard-wired loop to the actuator boards
        self.buttons_down = Buttons.NONE
        self.press_counts = [0, 0, 0, 0, 0]
        self.lamp_log: list[tuple[float, Lamps, str]] = []  # (time, lamps, text) on change
        self._holds: list[tuple[Buttons, float]] = []  # waiting for a step to start
        self._releases: list[tuple[Buttons, float]] = []

    @property
    def lamps(self) -> Lamps:
        return self.lamp_log[-1][1] if self.lamp_log else Lamps.NONE

    @property
    def display_text(self) -> str:
        return self.lamp_log[-1][2] if self.lamp_log else ""

    def press(self, name: str | Buttons) -> None:
        """A press and release quicker than one telemetry period: only the counter sees it."""
        self._count(_button(name))

    def hold(self, name: str | Buttons, seconds: float) -> None:
        button = _button(name)
        self._count(button)
        self.buttons_down |= button
        self._holds.append((button, seconds))

    def estop(self, pressed: bool) -> None:
        """Push (True) or twist-release (False) the mushroom; it also opens the wired loop."""
        if pressed and not self.buttons_down & Buttons.ESTOP:
            self._count(Buttons.ESTOP)
        if pressed:
            self.buttons_down |= Buttons.ESTOP
        else:
            self.buttons_down &= ~Buttons.ESTOP
        if self.on_estop is not None:
            self.on_estop(pressed)

    def _count(self, button: Buttons) -> None:
        index = BUTTON_ORDER.index(button)
        self.press_counts[index] = (self.press_counts[index] + 1) & 0xFF

    def is_release(self, command: PanelCommand) -> bool:
        return True

    def is_engaging(self, command: PanelCommand) -> bool:
        return False

    def _update(self, now_s: float, dt_s: float) -> None:
        self._releases += [(button, now_s + seconds) for button, seconds in self._holds]
        self._holds.clear()
        for button, release_s in list(self._releases):
            if now_s >= release_s:
                self.buttons_down &= ~button
                self._releases.remove((button, release_s))
        command = self.command
        if command is None:
            shown = (Lamps.OVERRIDE | Lamps.WARNING, HOST_LOST_TEXT)
        else:
            shown = (command.lamps, command.display_text)
        if not self.lamp_log or self.lamp_log[-1][1:] != shown:
            self.lamp_log.append((now_s, *shown))

    def telemetry(self, status: BoardStatus, fault: FaultCode, echo: int) -> PanelTelemetry:
        c = self.press_counts
        return PanelTelemetry(
            status, fault, echo, self.buttons_down, (c[0], c[1], c[2], c[3], c[4])
        )
