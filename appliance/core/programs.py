"""The maneuvers the daemon drives itself: the pedal sweep and the palm tree, on the core.

Armed by the maneuver request (`dbw calibrate pedals`, `dbw calibrate palm-tree --auto`:
"pedals[@N]", "palm-tree@N"), a program is the autopilot source while armed, in place of
the configured one, and its wish goes through the mode machine and the safety layer like
any source's: it has the vehicle only in SPEED_HOLD (with the engage button held where
hold-to-move asks for it, and always for the palm tree), and anything that takes the
vehicle away pauses it. Kept apart from the core's cycle because they are plans of their
own with their own arming rules; the core only asks for a wish, a refusal, a status.

A program disarmed while the operator is engaged (its command done, Ctrl-C, the client
gone) does not hand the vehicle back to the configured source, which may refuse where the
program left it and fault a vehicle at rest: its last wheel angle is held with no speed,
the core stopping and holding, until the operator takes over.
"""

from __future__ import annotations

import math
from typing import Any

from appliance.config import parts
from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig
from appliance.config.pedal_models import sweep_limit_problems
from appliance.core.observe import Measurements
from appliance.core.palm_tree_program import PalmTreeProgram, palm_tree_refusal
from appliance.core.wish import AutopilotWish
from appliance.guidance.palm_tree_drive import DriveCommand
from appliance.guidance.pedal_sweep import PedalSweep, SweepCommand
from appliance.modes import AUTOMATIC_MODES, Mode

PEDALS = "pedals"
PALM_TREE = "palm-tree"


class DrivenPrograms:
    """The armed program, if any (``reset()``, then ``wish()`` once per cycle)."""

    def __init__(self, config: VehicleConfig, calibration: Calibration | None) -> None:
        self.config = config
        self.calibration = calibration
        pedals = config.speed_path == "pedals"
        self.sweep = PedalSweep(parts.pedal_sweep_params(config)) if pedals else None
        self.reset()

    def reset(self) -> None:
        """A (re)started core: nothing armed (the client sees it and ends its run)."""
        self.sweeping = False
        self.last_sweep: SweepCommand | None = None
        self.palm: PalmTreeProgram | None = None
        self.ended_wish: AutopilotWish | None = None

    @staticmethod
    def drives(base: str, resumed: bool) -> bool:
        """Whether a maneuver's step text arms a program ("palm-tree" by hand does not)."""
        return base == PEDALS or (base == PALM_TREE and resumed)

    def refusal(
        self, base: str, resumed: bool, run_text: str, mode: Mode, speed_mps: float | None
    ) -> str | None:
        """Why the program may not be armed now (None: it may); ``resumed`` with a run or
        arc in ``run_text`` (the text after the @)."""
        if base == PEDALS:
            return self._sweep_refusal(resumed, run_text, mode, speed_mps)
        return palm_tree_refusal(self.config, self.calibration, mode, speed_mps, run_text)

    def arm(self, base: str, run_text: str) -> str:
        """Arm the program (its refusal said None); what the operator is told."""
        first = int(run_text) if run_text else 0
        if base == PEDALS and self.sweep is not None:
            self.sweep.reset(first)
            self.sweeping = True
            resumed = f" from run {first + 1}" if run_text else ""
            return f"; the pedal sweep is armed{resumed}: engage, then SPEED + to run it"
        if base == PALM_TREE and self.calibration is not None:
            self.palm = PalmTreeProgram(self.config, self.calibration, first)
            return (
                f"; the palm tree is armed from arc {first + 1} of "
                f"{self.palm.program.params.arcs}: engage, then SPEED + with ENGAGE held"
            )
        raise ValueError(f"no program to arm for {base!r}")  # refusal() said why first

    def disarm(self, mode: Mode) -> str | None:
        """Disarm what is armed; its name for the core's note (None: nothing was)."""
        if self.sweeping:
            self.sweeping = False
            name = "pedal_sweep"
            ended = AutopilotWish(
                ready=True, steer_tyre_rad=0.0, status={"pedal_sweep": {"phase": "ended"}}
            )
        elif self.palm is not None:
            name = "palm_tree"
            ended = self.palm.held()
            self.palm = None
        else:
            return None
        self.ended_wish = ended if mode in AUTOMATIC_MODES else None
        return name

    def wish(
        self, m: Measurements, now_s: float, mode: Mode, button_held: bool
    ) -> AutopilotWish | None:
        """The armed program's wish, or an ended one's hold; None: the configured source's.
        Judged on the mode the cycle starts in: the cycle's own events (a brake tap)
        still take the vehicle away before any command goes out."""
        if self.sweeping and self.sweep is not None:
            held = button_held or not self.config.engagement.hold_to_move
            return self._sweep_wish(m, now_s, mode is Mode.SPEED_HOLD and held, self.sweep)
        if self.palm is not None:
            # Hold-to-move is a condition of arming the palm tree: the button must be held.
            in_control = mode is Mode.SPEED_HOLD and button_held
            try:
                steering = mode in AUTOMATIC_MODES
                return self.palm.wish(m.steer_wheel_rad, m.speed_mps, now_s, in_control, steering)
            except Exception as exc:  # as for any source: a broken one is not ready
                return AutopilotWish(ready=False, reason=f"palm tree: {type(exc).__name__}: {exc}")
        if mode not in AUTOMATIC_MODES:
            self.ended_wish = None
        return self.ended_wish

    def tapped(self) -> tuple[SweepCommand | None, DriveCommand | None]:
        """What the maneuver tap files with each sample."""
        sweep = self.last_sweep if self.sweeping else None
        return sweep, None if self.palm is None else self.palm.last

    def status(self) -> dict[str, Any]:
        document: dict[str, Any] = {}
        if self.sweeping and self.last_sweep is not None:
            document["pedal_sweep"] = self.last_sweep.as_status()
        if self.palm is not None and self.palm.last is not None:
            document["palm_tree"] = self.palm.last.as_status()
        return document

    def _sweep_wish(
        self, m: Measurements, now_s: float, in_control: bool, sweep: PedalSweep
    ) -> AutopilotWish:
        """While the sweep is armed it is the source: straight ahead, its pedals."""
        try:
            command = sweep.update(m.speed_mps, now_s, in_control)
        except Exception as exc:  # as for any source: a broken one is not ready, no more
            self.last_sweep = None
            return AutopilotWish(ready=False, reason=f"pedal sweep: {type(exc).__name__}: {exc}")
        self.last_sweep = command
        return AutopilotWish(
            ready=True,
            steer_tyre_rad=0.0,
            pedals_pct=(command.throttle_pct, command.brake_pct) if in_control else None,
            status={"pedal_sweep": command.as_status()},
        )

    def _sweep_refusal(
        self, resumed: bool, run_text: str, mode: Mode, speed_mps: float | None
    ) -> str | None:
        """Only on the pedals path, from READY (not engaged: the operator engages
        knowingly, after), standing; a resumed one from one of its runs."""
        if self.sweep is None:
            return (
                'the pedal sweep needs speed_path = "pedals" (here the PC104 closes the speed loop)'
            )
        config = self.config
        problems = sweep_limit_problems(config.pedal_sweep, config.limits, config.engagement)
        if problems:
            return "the vehicle file's [pedal_sweep] does not fit its limits: " + "; ".join(
                problems
            )
        runs = self.sweep.params.runs
        if resumed and not (run_text.isdigit() and int(run_text) < runs):
            return f"the pedal sweep resumes from a run 0..{runs - 1}, not {run_text!r}"
        if mode is not Mode.READY:
            return f"the pedal sweep starts from READY, not {mode}"
        if speed_mps is None or not math.isfinite(speed_mps):
            return "the pedal sweep needs a measured speed (is the GNSS/INS fixed?)"
        if abs(speed_mps) > self.sweep.params.stopped_mps * 2.0:
            return f"the pedal sweep starts standing (moving at {abs(speed_mps):.2f} m/s)"
        return None
