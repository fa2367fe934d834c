"""The simulated world the twins share: one vehicle, stepped at a fixed rate.

Twins write the inputs they own into their own slot (``set_inputs("pc104", ...)``,
``set_inputs("brake_board", brake_pct=...)``, ``set_inputs("operator", brake_pct=...)``)
and the world merges them the way the physical vehicle does: the strongest brake wins,
the strongest throttle wins, the steering wheel (servo or operator) overrides the PC104's
front steering setpoint when it is set, and the motion pattern is the PC104's, or the
vehicle's natural one when no PC104 speaks. Twins read the pose they need (the scanner
twins the platform pose). Stepping is explicit (``advance_to``) so tests run as fast as
the CPU allows; ``run_realtime`` is the daemon's paced loop around the same step.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any, Literal

from appliance.sim.vehicle import (
    VehicleCommand,
    VehicleParams,
    VehicleState,
    step,
)
from drivers.pc104.messages import MotionPattern

# Sources that turn the steering wheel; the operator's hands are listed last and win.
STEERING_WHEEL_SOURCES = ("steering_servo", "operator")


class SimWorld:
    def __init__(
        self,
        params: VehicleParams,
        initial: VehicleState | None = None,
        step_hz: float = 100.0,
        steered_axle: Literal["front", "rear"] = "front",
    ) -> None:
        if step_hz <= 0:
            raise ValueError(f"step_hz must be positive (got {step_hz})")
        self.params = params
        self.step_s = 1.0 / step_hz
        self._initial = initial if initial is not None else VehicleState()
        self.state = self._initial
        self.command = VehicleCommand()
        # A forklift's steering wheel turns its rear axle (Kinouchi et al.'s AGF): the
        # wheel's tyre angle, positive turning left, is then the rear axle's in the
        # vehicle model's counter-steer sense, in the REAR_STEER pattern.
        self.steered_axle = steered_axle
        rear = steered_axle == "rear"
        self.default_pattern = MotionPattern.REAR_STEER if rear else MotionPattern.COUNTER_STEER
        self._inputs: dict[str, dict[str, Any]] = {}

    def reset(self, initial: VehicleState | None = None) -> None:
        if initial is not None:
            self._initial = initial
        self.state = self._initial
        self.command = VehicleCommand()
        self._inputs.clear()

    def update_command(self, **changes: Any) -> None:
        """Change part of the command directly (tests and scripted scenarios)."""
        self.command = replace(self.command, **changes)

    def set_inputs(self, source: str, **fields: Any) -> None:
        """Record what one source asks for and recompute the merged command.

        Fields: ``pattern``, ``front_steer_rad``, ``rear_steer_rad``, ``throttle_pct``,
        ``brake_pct``, ``reverse``. A source that stops (a twin losing its link) calls
        ``clear_inputs`` so its last wish does not linger.
        """
        unknown = set(fields) - set(VehicleCommand.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown vehicle inputs: {sorted(unknown)}")
        self._inputs.setdefault(source, {}).update(fields)
        self._merge()

    def clear_inputs(self, source: str) -> None:
        self._inputs.pop(source, None)
        self._merge()

    def _merge(self) -> None:
        slots = self._inputs
        pc104 = slots.get("pc104", {})
        wheel = [
            slots[name]["front_steer_rad"]
            for name in STEERING_WHEEL_SOURCES  # priority order: the operator's hands last
            if "front_steer_rad" in slots.get(name, {})
        ]
        front = wheel[-1] if wheel else pc104.get("front_steer_rad", 0.0)
        rear = pc104.get("rear_steer_rad", 0.0)
        if self.steered_axle == "rear":
            front, rear = 0.0, (wheel[-1] if wheel else rear)
        self.command = VehicleCommand(
            pattern=pc104.get("pattern", self.default_pattern),
            front_steer_rad=front,
            rear_steer_rad=rear,
            throttle_pct=max((s.get("throttle_pct", 0.0) for s in slots.values()), default=0.0),
            brake_pct=max((s.get("brake_pct", 0.0) for s in slots.values()), default=0.0),
            reverse=any(bool(s.get("reverse", False)) for s in slots.values()),
        )

    def advance_to(self, t_s: float) -> VehicleState:
        """Step at the fixed rate until the world time reaches ``t_s``."""
        while self.state.t_s + self.step_s <= t_s + 1e-12:
            self.state = step(self.state, self.command, self.step_s, self.params)
        return self.state

    async def run_realtime(
        self, on_step: Callable[[], None] | None = None, clock: Callable[[], float] = time.monotonic
    ) -> None:
        """Keep world time in step with ``clock`` (offset at start) until cancelled."""
        offset_s = clock() - self.state.t_s
        while True:
            self.advance_to(clock() - offset_s)
            if on_step is not None:
                on_step()
            await asyncio.sleep(self.step_s)
