"""The simulated vehicle's test bench: the operator's hands and feet, and the fault switches.

Why: the simulated vehicle runs in a process of its own (``appliance.sim_process``), so a
test, a benchmark or a developer cannot reach into its twins to press a panel button,
pull a board's cable or silence the PC104. The bench is that reach, as requests: each
one names an action on the twins, or asks what the twins were last told (``observe``).
It is the simulated vehicle's side only; the daemon is reached as on a vehicle, through
its devices and its control socket.

This module is the protocol's core, without I/O: a request (one JSON object) in, a reply
out. Every request is checked against its schema first, so a malformed or hostile one
gets an error reply naming the problem and changes nothing. The socket around it is
:mod:`appliance.sim.bench_socket`.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import time
from collections.abc import Callable, Mapping
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.twins.gnss import GnssTwin
from appliance.sim.twins.lms111 import Lms111Twin
from appliance.sim.twins.pc104 import Pc104Twin
from appliance.sim.world import SimWorld
from drivers.actuators.messages import BUTTON_ORDER, Buttons

BoardName = Literal["steering", "throttle", "brake", "panel"]
ButtonName = Literal["engage", "speed_plus", "speed_minus", "manual_override"]
Pct = Annotated[float, Field(ge=0.0, le=100.0, allow_inf_nan=False)]
# Long enough for a whole docking approach under hold-to-move, held from start to finish.
MAX_HOLD_S = 600.0
# Far beyond any wheel's travel: an operator cannot turn it further than this.
MAX_HANDS_WHEEL_RAD = 4.0 * math.pi

assert {b.name.lower() for b in BUTTON_ORDER if b.name} >= set(ButtonName.__args__)  # type: ignore[attr-defined]


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class Observe(_Request):
    """What the twins were last told and where the vehicle is; changes nothing."""

    op: Literal["observe"]


class Press(_Request):
    """A panel button pressed and released within one telemetry period."""

    op: Literal["press"]
    button: ButtonName


class Hold(_Request):
    op: Literal["hold"]
    button: ButtonName
    seconds: Annotated[float, Field(gt=0.0, le=MAX_HOLD_S, allow_inf_nan=False)]


class Estop(_Request):
    """The mushroom pushed (True) or twisted out (False); it also opens the wired loop."""

    op: Literal["estop"]
    pressed: bool


class Pedal(_Request):
    """The operator's foot resting on a pedal until changed (0: foot off)."""

    op: Literal["pedal"]
    pedal: Literal["throttle", "brake"]
    pct: Pct


class BrakeTap(_Request):
    op: Literal["brake_tap"]
    pct: Pct
    duration_s: Annotated[float, Field(gt=0.0, le=MAX_HOLD_S, allow_inf_nan=False)]


class Hands(_Request):
    """The operator grips the steering wheel at ``wheel_rad`` (null: lets go)."""

    op: Literal["hands"]
    wheel_rad: (
        Annotated[
            float, Field(ge=-MAX_HANDS_WHEEL_RAD, le=MAX_HANDS_WHEEL_RAD, allow_inf_nan=False)
        ]
        | None
    )


class Gear(_Request):
    """The operator's gear selector: forward, or reverse (the palm tree backs up its arcs).
    On a vehicle with a PC104 the PC104's own reverse counts as well."""

    op: Literal["gear"]
    reverse: bool


class Unplug(_Request):
    """The board's USB cable pulled: its tty goes away until ``replug``."""

    op: Literal["unplug", "replug"]
    board: BoardName


class Corrupt(_Request):
    """The board's next ``frames`` telemetry frames go out with a wrong CRC."""

    op: Literal["corrupt"]
    board: BoardName
    frames: Annotated[int, Field(ge=1, le=10_000)]


class Pc104Faults(_Request):
    """Switches of the PC104 twin; the ones not named keep their value."""

    op: Literal["pc104_faults"]
    drop_all: bool | None = None
    drop_one_in: Annotated[int, Field(ge=0, le=1000)] | None = None
    delay_s: Annotated[float, Field(ge=0.0, le=5.0, allow_inf_nan=False)] | None = None
    bad_crc: bool | None = None
    stuck_counter: bool | None = None
    bus_off: bool | None = None
    error_passive: bool | None = None
    cab_control: bool | None = None


class Pc104Restart(_Request):
    """The PC104 reboots: counters start over, nothing commanded survives."""

    op: Literal["pc104_restart"]


class GnssSignal(_Request):
    """The GNSS/INS antenna shadowed (the receiver talks on but sends no epochs) or clear,
    or its cable pulled and plugged again (``plugged``)."""

    op: Literal["gnss_signal"]
    on: bool | None = None
    plugged: bool | None = None


class ScannerPower(_Request):
    """A scanner powered off (listener and connections gone) or on again."""

    op: Literal["scanner_power"]
    side: Literal["left", "right"]
    on: bool


Request = Annotated[
    Observe
    | Press
    | Hold
    | Estop
    | Pedal
    | BrakeTap
    | Hands
    | Gear
    | Unplug
    | Corrupt
    | Pc104Faults
    | Pc104Restart
    | ScannerPower
    | GnssSignal,
    Field(discriminator="op"),
]
_REQUEST: TypeAdapter[Request] = TypeAdapter(Request)
OPS = (
    "observe",
    "press",
    "hold",
    "estop",
    "pedal",
    "brake_tap",
    "hands",
    "gear",
    "unplug",
    "replug",
    "corrupt",
    "pc104_faults",
    "pc104_restart",
    "scanner_power",
    "gnss_signal",
)


class BenchRequestError(ValueError):
    """A request that is not one the bench knows; the message says what is wrong."""


def parse_request(message: object) -> Request:
    """The typed request, or :class:`BenchRequestError` naming every problem."""
    if not isinstance(message, Mapping):
        raise BenchRequestError(
            f'a request is a JSON object, e.g. {{"op": "observe"}}; got {type(message).__name__}'
        )
    if message.get("op") not in OPS:
        raise BenchRequestError(f"unknown op {message.get('op')!r}: known ops are {', '.join(OPS)}")
    try:
        return _REQUEST.validate_python(dict(message))
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(part) for part in error['loc'][1:]) or 'request'}: {error['msg']}"
            for error in exc.errors(include_url=False)
        )
        raise BenchRequestError(f"bad {message['op']!r} request: {problems}") from None


def _plain(value: Any) -> Any:
    """Commands and states as JSON: enums by name, flags as the list of their names."""
    if isinstance(value, enum.Flag):
        return [
            member.name.lower()
            for member in type(value)
            if member.name and member.value and member in value
        ]
    if isinstance(value, enum.Enum):
        return str(value.name).lower()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    raise TypeError(f"no JSON form for {type(value).__name__}")


class SimBench:
    """The actions a bench offers on one simulated vehicle's twins."""

    def __init__(
        self,
        world: SimWorld,
        boards: ActuatorTwins,
        pc104: Pc104Twin | None,
        scanners: Mapping[str, Lms111Twin],
        *,
        gnss: GnssTwin | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.world = world
        self.gnss = gnss
        self.boards = boards
        self.pc104 = pc104
        self.scanners = dict(scanners)
        self.clock = clock

    async def handle(self, message: object) -> dict[str, Any]:
        """One request, one reply: ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``."""
        try:
            request = parse_request(message)
            return {"ok": True, **(await self._apply(request))}
        except BenchRequestError as exc:
            return {"ok": False, "error": str(exc)}

    async def _apply(self, request: Request) -> dict[str, Any]:
        boards = self.boards
        match request:
            case Observe():
                return {"state": self.observe()}
            case Press(button=button):
                boards.panel.press(button)
            case Hold(button=button, seconds=seconds):
                boards.panel.hold(button, seconds)
            case Estop(pressed=pressed):
                boards.panel.estop(pressed)
            case Pedal(pedal="throttle", pct=pct):
                boards.throttle.operator_pedal(pct)
            case Pedal(pct=pct):
                boards.brake.operator_pedal(pct)
            case BrakeTap(pct=pct, duration_s=duration_s):
                boards.brake.operator_brake_tap(pct, duration_s)
            case Hands(wheel_rad=wheel_rad):
                boards.steering.operator_hands(wheel_rad)
            case Gear(reverse=reverse):
                self.world.set_inputs("operator", reverse=reverse)
            case Unplug(op="unplug", board=board):
                boards.boards[board].unplug()
            case Unplug(board=board):
                boards.boards[board].replug()
            case Corrupt(board=board, frames=frames):
                boards.boards[board].corrupt_next_frames(frames)
            case Pc104Faults():
                faults = self._pc104().faults
                for name, value in request.model_dump(exclude={"op"}, exclude_none=True).items():
                    setattr(faults, name, value)
                return {"pc104_faults": _plain(faults)}
            case Pc104Restart():
                self._pc104().restart()
            case ScannerPower(side=side, on=on):
                twin = self.scanners.get(side)
                if twin is None:
                    raise BenchRequestError(f"this simulated vehicle has no {side} scanner")
                if on:
                    await twin.power_on()
                else:
                    await twin.stop()
            case GnssSignal(on=on, plugged=plugged):
                if self.gnss is None:
                    raise BenchRequestError("this simulated vehicle has no GNSS/INS receiver")
                if on is not None:
                    self.gnss.synth.shadowed = not on
                if plugged is True:
                    self.gnss.replug()
                elif plugged is False:
                    self.gnss.unplug()
        return {}

    def _pc104(self) -> Pc104Twin:
        if self.pc104 is None:
            raise BenchRequestError("this simulated vehicle has no PC104 (no CAN endpoint)")
        return self.pc104

    def observe(self) -> dict[str, Any]:
        """What every twin was last told, as plain JSON (commands by their fields)."""
        boards = self.boards
        state = self.world.state
        steering, throttle, brake = boards.steering, boards.throttle, boards.brake
        panel = boards.panel
        return {
            "now_s": self.clock(),
            "world": {
                "x_m": state.x_m,
                "y_m": state.y_m,
                "yaw_rad": state.yaw_rad,
                "platform_yaw_rad": state.platform_yaw_rad,  # where the scanners look from
                "speed_mps": state.speed_mps,
            },
            "steering": {
                "command": _plain(steering.command),
                "plugged": steering.link.plugged,
                "wheel_angle_rad": steering.wheel_angle_rad,
                "steering_ratio": steering.params.steering_ratio,
            },
            "throttle": {
                "command": _plain(throttle.command),
                "plugged": throttle.link.plugged,
                "actuator_position_pct": throttle.actuator_position_pct,
                "pedal_position_pct": throttle.pedal_position_pct,
            },
            "brake": {
                "command": _plain(brake.command),
                "plugged": brake.link.plugged,
                "actuator_position_pct": brake.actuator_position_pct,
                "pedal_position_pct": brake.pedal_position_pct,
            },
            "panel": {
                "plugged": panel.link.plugged,
                "lamps": _plain(panel.lamps),
                "display_text": panel.display_text,
                "estop": bool(panel.buttons_down & Buttons.ESTOP),
            },
            "pc104": None if self.pc104 is None else self._observe_pc104(self.pc104),
            "scanners": {side: {"powered": twin.running} for side, twin in self.scanners.items()},
            "gnss": None
            if self.gnss is None
            else {
                "plugged": self.gnss.link.plugged,
                "shadowed": self.gnss.synth.shadowed,
                "epochs": self.gnss.synth.epochs,
                "dropped_epochs": self.gnss.synth.dropped_epochs,
            },
        }

    @staticmethod
    def _observe_pc104(twin: Pc104Twin) -> dict[str, Any]:
        core = twin.core
        command = core.command
        return {
            "command_pattern": None if command is None else _plain(command.pattern),
            "applied_pattern": _plain(core.applied_pattern),
            "hl_state": _plain(core.hl_state),
            "faults": _plain(core.faults),
        }
