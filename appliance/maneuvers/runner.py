"""Running one calibration maneuver against the daemon: check, tap, watch, stop.

The daemon stays in charge of the vehicle the whole time: the runner only asks it to tap
its cycles (``appliance.core.maneuver_tap``) and reads the samples back, so nothing here
can command an actuator, and whatever the runner does (or fails to do) the mode machine
and the safety layer act as they always do. A maneuver the technician performs by hand
(pot centre, pot map, a palm tree driven as in the paper) needs nothing more. The pedal
sweep's start also arms the daemon's own sweep program (``appliance.guidance.
pedal_sweep``), whose pedals the operator hands over by engaging and the mode machine
takes back as from any source; its stop (whichever way the run ended) disarms it.

The runner ends a run for exactly one reason, said in words: the step is complete, the
technician pressed Ctrl-C, the time ran out, the daemon went away, or a sample showed
something that makes the data worthless or the maneuver unsafe (a fault, the e-stop,
a stale input the step needs, the step's own rules: moving during a stationary step).
In every case the tap is stopped and the samples taken so far are on disk, so the run
can be resumed; the calibration file is touched only after a complete run's fit was
accepted (``appliance.maneuvers.merge``).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, TextIO

from appliance.control_client import ControlClient
from appliance.control_protocol import ControlSocketError
from appliance.maneuvers.samples_file import SamplesWriter

POLL_S = 0.2  # ten cycles at 50 Hz per reply: far below the ring's ten minutes
PROGRESS_EVERY_S = 1.0
COUNTDOWN_S = 3
FAULT_MODES = frozenset({"error", "estop"})


@dataclass(frozen=True)
class Progress:
    """How far a step is: ``fraction`` 0..1, a coverage bar, and a line of detail."""

    fraction: float
    bar: str
    detail: str


class ManeuverStep(Protocol):
    """One maneuver's rules; the samples are the tap's dictionaries."""

    name: ClassVar[str]
    instructions: tuple[str, ...]
    moves_vehicle: bool
    needed_inputs: tuple[str, ...]  # stale in a sample: the run is aborted
    # Faults that are what the step measures, not a reason to stop it (the pot map on a
    # vehicle whose old calibration no longer covers the pot's readings). The daemon's
    # safe state still holds: only the run goes on.
    tolerated_faults: frozenset[str]

    def preconditions(self, status: Mapping[str, Any]) -> list[str]: ...

    def start_step(self) -> str:
        """What the start request names: the step, or where a resumed run goes on from."""
        ...

    def reset(self) -> None: ...

    def update(self, sample: Mapping[str, Any]) -> str | None:
        """Take one sample; a text ends the run (the maneuver broke a rule)."""
        ...

    def progress(self) -> Progress: ...

    def complete(self) -> bool: ...


@dataclass(frozen=True)
class RunOutcome:
    complete: bool
    reason: str  # why the run ended, in words
    samples: int  # taken in this run
    missed: int  # lost between the daemon's ring and this client (a slow poll)


class RefusedError(Exception):
    """The maneuver cannot start; the message lists every failed precondition."""


def common_problems(status: Mapping[str, Any], step: ManeuverStep) -> list[str]:
    """Preconditions every maneuver shares: no fault, no e-stop, fresh inputs, idle tap."""
    problems = []
    mode = str(status.get("mode", "unknown"))
    faults = {str(f.get("key")) for f in status.get("faults", []) if isinstance(f, dict)}
    untolerated = sorted(faults - step.tolerated_faults)
    if mode == "estop" or status.get("estop_latched"):
        problems.append("the e-stop is latched: release and reset it first")
    elif mode in FAULT_MODES and (untolerated or not faults):
        problems.append(f"the daemon is in {mode.upper()}: clear the fault first")
    if untolerated:
        problems.append(f"active faults: {', '.join(untolerated)}")
    inputs = status.get("inputs") or {}
    stale = [name for name in step.needed_inputs if _stale(inputs, name)]
    if stale:
        problems.append(f"inputs not fresh: {', '.join(stale)}")
    maneuver = status.get("maneuver")
    if isinstance(maneuver, dict) and maneuver.get("active"):
        problems.append(f"maneuver {maneuver.get('step')!r} is already running")
    return problems


def _stale(inputs: Mapping[str, Any], name: str) -> bool:
    """Stale by the daemon's own limit; never received at all is stale too."""
    entry = inputs.get(name)
    return not isinstance(entry, dict) or entry.get("age_s") is None or bool(entry.get("stale"))


def sample_problem(sample: Mapping[str, Any], step: ManeuverStep) -> str | None:
    """What in a sample ends every maneuver: a fault, the e-stop, a needed input stale."""
    mode = str(sample.get("mode"))
    faults = set(sample.get("faults") or ())
    if mode == "estop" or (mode in FAULT_MODES and not faults <= step.tolerated_faults):
        named = ", ".join(sorted(faults - step.tolerated_faults)) or "none named"
        return f"the daemon went to {mode.upper()} (faults: {named})"
    stale = [name for name in step.needed_inputs if name in (sample.get("stale") or ())]
    if stale:
        return f"input stale: {', '.join(stale)}"
    return None


def eta_text(elapsed_s: float, fraction: float) -> str:
    if fraction <= 0.02 or fraction >= 1.0:
        return "ETA --"
    remaining = elapsed_s * (1.0 - fraction) / fraction
    return f"ETA {int(remaining // 60)}:{int(remaining % 60):02d}"


class ManeuverRunner:
    """One run of one step: ``await run()`` returns why it ended."""

    def __init__(
        self,
        step: ManeuverStep,
        client: ControlClient,
        writer: SamplesWriter,
        out: TextIO,
        *,
        timeout_s: float,
        confirm: Callable[[str], bool],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.step = step
        self.client = client
        self.writer = writer
        self.out = out
        self.timeout_s = timeout_s
        self.confirm = confirm
        self.clock = clock
        self.samples = 0
        self.missed = 0
        self._since = 0  # the next sample to ask the daemon for

    def say(self, text: str) -> None:
        self.out.write(text + "\n")
        self.out.flush()

    async def check(self) -> None:
        """Every precondition, from one status document; raise RefusedError with all
        that fail."""
        status = (await self.client.status()).get("status", {})
        problems = common_problems(status, self.step) + self.step.preconditions(status)
        if problems:
            raise RefusedError("; ".join(problems))

    async def run(self) -> RunOutcome:
        await self.check()
        for line in self.step.instructions:
            self.say(line)
        question = (
            "The vehicle will move. Is the area clear and is someone at the controls?"
            if self.step.moves_vehicle
            else "Ready to start (the daemon only watches; you do the moving)?"
        )
        if not self.confirm(question):
            raise RefusedError("not confirmed by the operator")
        # The answer may take longer than the daemon keeps an idle connection, and the
        # vehicle may have changed meanwhile: a new connection, every check again.
        await self.client.close()
        await self.check()
        if self.step.moves_vehicle:
            for left in range(COUNTDOWN_S, 0, -1):
                self.say(f"  starting in {left} ...")
                await asyncio.sleep(1.0)
        reply = await self.client.call(
            {"op": "maneuver", "action": "start", "step": self.step.start_step()}
        )
        if not reply.get("accepted"):
            raise RefusedError(f"the daemon refused: {reply.get('message') or reply.get('error')}")
        self.writer.mark("started", message=reply.get("message"))
        reason = "stopped"
        try:
            reason = await self._watch()
        except asyncio.CancelledError:
            reason = "interrupted (Ctrl-C)"
            raise
        except ControlSocketError as exc:
            reason = f"lost the daemon: {exc}"
        finally:
            await self._stop(reason)
        return RunOutcome(reason == "complete", reason, self.samples, self.missed)

    async def _watch(self) -> str:
        status = (await self.client.status()).get("status", {})
        maneuver = status.get("maneuver") or {}
        self._since = int(maneuver.get("first_seq", 0))
        started = self.clock()
        shown = started
        while True:
            reply = await self._poll()
            if isinstance(reply, str):
                return reply
            batch = reply.get("samples") or []
            # Where each sample stands, so that an abort mid-batch leaves the rest to `_drain`.
            first = int(reply.get("next", self._since + len(batch))) - len(batch)
            for offset, sample in enumerate(batch, start=1):
                problem = sample_problem(sample, self.step) or self.step.update(sample)
                self.writer.append([sample])
                self.samples += 1
                self._since = first + offset
                if problem is not None:
                    return f"aborted: {problem}"
            if not reply.get("active", False):
                return "aborted: the daemon stopped the tap (restarted?)"
            if self.step.complete():
                return "complete"
            now = self.clock()
            if now - started > self.timeout_s:
                return f"aborted: not complete within {self.timeout_s:.0f} s"
            if now - shown >= PROGRESS_EVERY_S:
                shown = now
                self._show_progress(now - started)
            if len(batch) < 50:
                await asyncio.sleep(POLL_S)

    def _show_progress(self, elapsed_s: float) -> None:
        progress = self.step.progress()
        self.say(
            f"  [{progress.bar}] {100.0 * progress.fraction:3.0f} %  {progress.detail}  "
            f"{eta_text(elapsed_s, progress.fraction)}"
        )

    async def _poll(self) -> dict[str, Any] | str:
        """The daemon's samples from ``_since`` on, or why it refused them; any it no
        longer had are counted and marked in the file."""
        reply = await self.client.call({"op": "samples", "since": self._since})
        if reply.get("ok") is not True:
            return f"the daemon refused the samples: {reply.get('error')}"
        lost = int(reply.get("missed", 0))
        if lost:
            self.missed += lost
            self.writer.mark("missed", samples=lost)
        return reply

    async def _drain(self) -> None:
        """What the tap took between our last poll and its stop: the file holds every
        sample the daemon tapped, as its flight recording replays them (the run is over:
        they are kept, not judged)."""
        while isinstance(reply := await self._poll(), dict):
            batch = reply.get("samples") or []
            self.writer.append(batch)
            self.samples += len(batch)
            self._since = int(reply.get("next", self._since))
            # A tap still running was not stopped by us (another step's): no end to wait for.
            if not batch or reply.get("active", False):
                return

    async def _stop(self, reason: str) -> None:
        # The daemon gone, or we are: its tap is only a reader either way.
        with contextlib.suppress(ControlSocketError, asyncio.CancelledError, OSError):
            await asyncio.shield(
                self.client.call({"op": "maneuver", "action": "stop", "step": self.step.name})
            )
            await asyncio.shield(self._drain())
        self.writer.mark("stopped", reason=reason)
