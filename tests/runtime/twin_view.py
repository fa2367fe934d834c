"""The simulated vehicle's twins, seen and driven from a test through its bench socket.

The daemon under test runs its simulated vehicle in a child process, as `dbw run --config
sim` does, so the control loop shares its event loop with nothing but the test. A test
acts as the operator (press a button, rest a foot, grip the wheel) and flips fault
switches with :meth:`TwinView.act`; what the twins were last told is polled in the
background every ``poll_s`` and read synchronously, so the tests' predicates stay plain
functions.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

from appliance.control_client import ControlClient
from appliance.control_protocol import ControlSocketError
from drivers.actuators.messages import BrakeCommand, Lamps, SteeringMode
from drivers.pc104.messages import HighLevelState, MotionPattern

BENCH_POLL_S = 0.005  # the resolution of a latency measured at a twin


def _named(enum_type: Any, name: str | None) -> Any:
    return None if name is None else enum_type[name.upper()]


class TwinView:
    """The latest observation of every twin, and the bench's actions."""

    def __init__(self, path: str, poll_s: float = BENCH_POLL_S) -> None:
        self.path = path
        self.poll_s = poll_s
        self.state: dict[str, Any] = {}
        self.observed_s = -1.0  # when ``state`` was taken (the child's monotonic clock)
        self.poll_errors: list[str] = []
        self._actions = ControlClient(path, timeout_s=5.0)
        self._observer = ControlClient(path, timeout_s=5.0)
        self._observing = asyncio.Lock()  # one request at a time on the observer's connection
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Connect, take the first observation, and keep observing in the background."""
        await self.refresh()
        self._task = asyncio.create_task(self._poll(), name="twin-view")

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await self._actions.close()
        await self._observer.close()

    async def act(self, op: str, **fields: Any) -> dict[str, Any]:
        """One bench action; fails the test if the bench refused it."""
        reply = await self._actions.call({"op": op, **fields})
        assert reply["ok"], (op, fields, reply)
        return reply

    async def refresh(self) -> dict[str, Any]:
        """A new observation now (for a check right after an action or a wait)."""
        async with self._observing:
            reply = await self._observer.call({"op": "observe"})
        assert reply["ok"], reply
        state: dict[str, Any] = reply["state"]
        if state["now_s"] > self.observed_s:
            self.state, self.observed_s = state, state["now_s"]
        return state

    async def _poll(self) -> None:
        while True:
            try:
                await self.refresh()
            except ControlSocketError as exc:  # shown by the failing test's status
                self.poll_errors.append(f"{time.monotonic():.3f}: {exc}")
                await asyncio.sleep(0.1)
            await asyncio.sleep(self.poll_s)

    # ---- what the twins were told (from the latest observation) -----------------------
    def steering_mode(self) -> SteeringMode | None:
        command = self.state["steering"]["command"]
        return None if command is None else _named(SteeringMode, command["mode"])

    def steering_commanded(self) -> bool:
        """False once the board's command timed out (it follows no host command)."""
        return self.state["steering"]["command"] is not None

    def pc104_pattern(self) -> MotionPattern | None:
        pattern: MotionPattern | None = _named(
            MotionPattern, self.state["pc104"]["command_pattern"]
        )
        return pattern

    def pc104_applied(self) -> MotionPattern:
        pattern: MotionPattern = _named(MotionPattern, self.state["pc104"]["applied_pattern"])
        return pattern

    def pc104_moving(self) -> bool:
        pattern = self.pc104_pattern()
        return pattern is not None and pattern is not MotionPattern.STOP

    def hl_state(self) -> HighLevelState | None:
        """The high level's state in the last HL_Heartbeat the PC104 heard."""
        state: HighLevelState | None = _named(HighLevelState, self.state["pc104"]["hl_state"])
        return state

    def brake_command(self) -> BrakeCommand | None:
        command = self.state["brake"]["command"]
        return None if command is None else BrakeCommand(**command)

    def brake_applied(self) -> bool:
        command = self.brake_command()
        return command is not None and command.enable

    def brake_actuator_pct(self) -> float:
        pct: float = self.state["brake"]["actuator_position_pct"]
        return pct

    def lamps(self) -> Lamps:
        lamps = Lamps.NONE
        for name in self.state["panel"]["lamps"]:
            lamps |= Lamps[name.upper()]
        return lamps

    def display_text(self) -> str:
        text: str = self.state["panel"]["display_text"]
        return text

    def speed_mps(self) -> float:
        speed: float = self.state["world"]["speed_mps"]
        return speed
