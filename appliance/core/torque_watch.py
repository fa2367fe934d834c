"""Has the steering servo's torque changed since the look-ahead was tuned? Asked while driving.

Stanley et al. (Fig. 21): when a voltage change lowered the servo's torque, the tuned
look-ahead no longer kept the vehicle stable. `dbw calibrate lookahead` keeps the servo's
load over its runs as a baseline (``[guidance.servo_torque]``); this watches the same
telemetry whenever the daemon steers (the wheel's angle from the servo's encoder, its
rate, the servo's torque) and compares a recent window with the baseline by
``calibration.servo_torque.compare_torque``. A change past its thresholds is a flag in the
status and a log event, not a fault: the vehicle still steers, the schedule is what may
no longer suit it, and re-tuning is the technician's call.

Pure: samples and time in, a verdict out; the fit runs once per ``every`` samples, every
ten seconds at 50 Hz (0.3 ms median, 0.5 ms p99 for a full window, measured on the
development machine).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from calibration.servo_torque import (
    TorqueComparison,
    TorqueParams,
    TorqueStats,
    compare_torque,
    torque_stats,
)

WINDOW_SAMPLES = 3000  # a minute of steering at 50 Hz
EVERY_SAMPLES = 500


class TorqueWatch:
    """The recent window and the verdict against the baseline (``reset()``/``update()``)."""

    def __init__(
        self,
        baseline: TorqueStats,
        params: TorqueParams | None = None,
        window: int = WINDOW_SAMPLES,
        every: int = EVERY_SAMPLES,
    ) -> None:
        self.baseline = baseline
        self.params = params if params is not None else TorqueParams()
        self.every = every
        # The window as a ring of rows (wheel, rate, torque): the fit does not care about
        # their order, so it reads the filled rows as they lie, without a copy per cycle.
        self._rows = np.empty((window, 3))
        self._filled = 0
        self._next = 0
        self.last: TorqueComparison | None = None
        self.problem = "not enough steering yet"
        self.reset()

    def reset(self) -> None:
        """A new engagement: the rate is not taken across the gap."""
        self._previous: tuple[float, float] | None = None
        self._since = 0

    def update(
        self,
        now_s: float,
        steering: bool,
        wheel_rad: float | None,
        encoder_rad: float | None,
        torque_nm: float | None,
    ) -> TorqueComparison | None:
        """One cycle: the wheel's angle (the pot through the calibration), the servo's
        encoder (its rate: smoother than the pot's, and the encoder's offset does not
        matter there), the servo's torque. Returns a new comparison when one was made."""
        values = (now_s, wheel_rad, encoder_rad, torque_nm)
        if not steering or not all(v is not None and math.isfinite(v) for v in values):
            self._previous = None
            return None
        assert wheel_rad is not None and encoder_rad is not None and torque_nm is not None
        previous, self._previous = self._previous, (now_s, encoder_rad)
        if previous is None or now_s <= previous[0]:
            return None
        rate = (encoder_rad - previous[1]) / (now_s - previous[0])
        self._rows[self._next] = (wheel_rad, rate, torque_nm)
        self._next = (self._next + 1) % len(self._rows)
        self._filled = min(self._filled + 1, len(self._rows))
        self._since += 1
        if self._since < self.every:
            return None
        self._since = 0
        rows = self._rows[: self._filled]
        try:
            current = torque_stats(rows[:, 0], rows[:, 1], rows[:, 2], self.params)
        except ValueError as exc:
            self.problem = str(exc)
            return None
        self.problem = ""
        self.last = compare_torque(self.baseline, current, self.params)
        return self.last

    def status(self) -> dict[str, Any]:
        last = self.last
        if last is None:
            return {"retune": None, "reason": self.problem}
        return {
            "retune": last.retune,
            "change_pct": round(100.0 * last.relative_change, 1),
            "stall_change_pct": round(100.0 * last.stall_fraction_change, 1),
            "reason": "; ".join(last.reasons),
        }
