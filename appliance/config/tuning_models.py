"""The vehicle file's ``[lookahead_tuning]``: the runs `dbw calibrate lookahead` drives.

In the vehicle file, like ``[pedal_sweep]``, because the daemon lays the runs' courses and
a recording's replay must lay the same ones; and the fit's grid is the runs' candidates.
The defaults are Stanley et al.'s tests (line and arc at 0 and ±3 m parallel offsets, 5
and 10 mph) with three candidate gains around the tracker's default schedule: 36 runs of
about a minute each, every one from a standstill at a place with the course's room
(``room_m``), so an afternoon with the repositioning; a site with less room or time
lists fewer conditions or candidates.
"""

from __future__ import annotations

import math
from typing import Literal, Protocol, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from appliance.guidance.lookahead_tuning import TuningParams, TuningRun
from appliance.guidance.pure_pursuit import LookaheadSchedule
from calibration.lookahead import LookaheadParams, candidate_grid


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class TuningCondition(_Model):
    course: Literal["line", "arc_left", "arc_right"]
    offset_m: float = Field(ge=-5.0, le=5.0)  # the vehicle left of its course after the step


_PAPER_CONDITIONS = tuple(
    TuningCondition(course=course, offset_m=offset)
    for course in ("line", "arc_left")
    for offset in (0.0, 3.0, -3.0)
)


class LookaheadTuningSettings(_Model):
    speeds_mps: tuple[float, ...] = Field((2.235, 4.47), min_length=1)  # 5 and 10 mph
    conditions: tuple[TuningCondition, ...] = Field(_PAPER_CONDITIONS, min_length=1)
    # The candidates L(v) = clamp(offset + gain v, min, max): every offset with every
    # gain (schedules alike at every test speed are one).
    offsets_m: tuple[float, ...] = Field((0.5,), min_length=1)
    # Around the tracker's default schedule (0.5 + 0.5 s x v), 30 % either way: fine enough
    # to land near the best (on the simulated Husky the score rises steeply below 0.4 s,
    # the weave, and gently above, the arc cut short), coarse enough for an afternoon.
    gains_s: tuple[float, ...] = Field((0.35, 0.5, 0.65), min_length=1)
    min_m: float = Field(1.5, gt=0.0, le=50.0)
    max_m: float = Field(12.0, gt=0.0, le=100.0)
    arc_radius_m: float = Field(25.0, gt=2.0, le=500.0)
    runup_m: float = Field(30.0, gt=0.0, le=500.0)
    test_s: float = Field(25.0, gt=0.0, le=300.0)
    stop_m: float = Field(30.0, gt=0.0, le=500.0)
    # The fit (calibration.lookahead): after capture, this long a test is scored.
    min_scored_s: float = Field(10.0, gt=0.0, le=300.0)
    max_rms_m: float = Field(0.3, gt=0.0, le=5.0)
    max_overshoot_m: float = Field(0.3, gt=0.0, le=5.0)

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if self.max_m < self.min_m:
            raise ValueError("lookahead_tuning.max_m must not be below min_m")
        if any(not (v > 0.0 and math.isfinite(v)) for v in self.speeds_mps):
            raise ValueError("lookahead_tuning.speeds_mps must be positive")
        return self

    def candidates(self) -> tuple[LookaheadSchedule, ...]:
        return tuple(
            LookaheadSchedule(c.offset_m, c.gain_s, c.min_m, c.max_m)
            for c in candidate_grid(
                self.offsets_m,
                self.gains_s,
                min_m=self.min_m,
                max_m=self.max_m,
                speeds_mps=self.speeds_mps,
            )
        )

    def params(self, floor_m: float = 0.0) -> TuningParams:
        """The runs in the order driven: speed, then condition, then look-ahead (one
        set-up, every candidate on it in turn). Candidates with the same look-ahead at a
        speed (to 1 cm; ``floor_m`` is the tracker's own floor) share that speed's runs:
        the same test need not be driven twice."""
        candidates = self.candidates()
        runs: list[TuningRun] = []
        for speed in self.speeds_mps:
            alike: dict[int, list[int]] = {}
            for i, schedule in enumerate(candidates):
                key = round(100.0 * max(floor_m, schedule.lookahead_m(speed)))
                alike.setdefault(key, []).append(i)
            for condition in self.conditions:
                for group in alike.values():
                    runs.append(
                        TuningRun(
                            len(runs),
                            candidates[group[0]],
                            condition.course,
                            condition.offset_m,
                            speed,
                            tuple(group),
                        )
                    )
        return TuningParams(
            runs=tuple(runs),
            arc_radius_m=self.arc_radius_m,
            runup_m=self.runup_m,
            test_s=self.test_s,
            stop_m=self.stop_m,
        )

    def fit_params(self) -> LookaheadParams:
        return LookaheadParams(
            min_scored_s=self.min_scored_s,
            max_rms_m=self.max_rms_m,
            max_overshoot_m=self.max_overshoot_m,
        )


class _Limits(Protocol):
    @property
    def max_speed_mps(self) -> float: ...


class _Engagement(Protocol):
    @property
    def max_set_speed_mps(self) -> float: ...


def tuning_problems(
    tuning: LookaheadTuningSettings,
    limits: _Limits,
    engagement: _Engagement,
    min_turn_radius_m: float,
    lateral_accel_mps2: float,
) -> list[str]:
    """What in the tuning the vehicle would refuse or slow for (empty: nothing): a run not
    at its speed is not the run the fit scores."""
    problems = []
    top = max(tuning.speeds_mps)
    cap = min(limits.max_speed_mps, engagement.max_set_speed_mps)
    if top > cap:
        problems.append(
            f"lookahead_tuning.speeds_mps goes to {top:.2f} m/s, past the set speed's "
            f"limit ({cap:.2f} m/s)"
        )
    arcs = [c for c in tuning.conditions if c.course != "line"]
    if arcs:
        tightest = tuning.arc_radius_m - max(abs(c.offset_m) for c in arcs)
        if tightest < min_turn_radius_m * 1.2:
            problems.append(
                f"lookahead_tuning.arc_radius_m {tuning.arc_radius_m} m less the offsets "
                f"({tightest:.1f} m) is too tight for a {min_turn_radius_m:.1f} m turning "
                "radius and room to correct"
            )
        if top**2 / tuning.arc_radius_m > lateral_accel_mps2:
            problems.append(
                f"at {top:.2f} m/s a {tuning.arc_radius_m} m arc needs "
                f"{top**2 / tuning.arc_radius_m:.2f} m/s² sideways, more than "
                f"route.lateral_accel_mps2 ({lateral_accel_mps2}): the profile would slow "
                "the run; make the arc wider"
            )
    return problems


def room_m(tuning: LookaheadTuningSettings) -> float:
    """How far ahead the longest run's course reaches from where the vehicle stands."""
    params = tuning.params()
    return max(
        params.runup_m + run.speed_mps * params.test_s_for(run) + params.stop_m
        for run in params.runs
    )
