"""The simulated world the twins share: one vehicle, stepped at a fixed rate.

Twins write the parts of the command they own (the PC104 twin the pattern and wheel
angles, the actuator twins throttle and brake) and read the pose they need (the scanner
twins the platform pose). Stepping is explicit (``advance_to``) so tests run as fast as
the CPU allows; ``run_realtime`` is the daemon's paced loop around the same step.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step


class SimWorld:
    def __init__(
        self,
        params: VehicleParams,
        initial: VehicleState | None = None,
        step_hz: float = 100.0,
    ) -> None:
        if step_hz <= 0:
            raise ValueError(f"step_hz must be positive (got {step_hz})")
        self.params = params
        self.step_s = 1.0 / step_hz
        self._initial = initial if initial is not None else VehicleState()
        self.state = self._initial
        self.command = VehicleCommand()

    def reset(self, initial: VehicleState | None = None) -> None:
        if initial is not None:
            self._initial = initial
        self.state = self._initial
        self.command = VehicleCommand()

    def update_command(self, **changes: Any) -> None:
        """Change part of the command, leaving what other twins set untouched."""
        self.command = replace(self.command, **changes)

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
