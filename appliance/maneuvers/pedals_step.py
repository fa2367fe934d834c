"""`dbw calibrate pedals`: throttle and brake sweeps, driven by the daemon, into pedal maps.

The one step that moves the vehicle by program. The client arms the daemon's pedal sweep
(``appliance.guidance.pedal_sweep``, armed by the maneuver request), the operator engages
and presses SPEED + (holding the engage button where the vehicle uses hold-to-move), and
the daemon runs the sweep's levels through its usual arbitration and limits; anything that
takes the pedals away (a brake tap, the wheel, the override, a fault) pauses it. This side
only watches: it files each cycle in which the sweep had the pedals (SPEED_HOLD, a throttle,
boost, descend, coast or brake phase) as a sample of measured actuator positions and speed,
shows the
grid filling, and fits when the sweep says it is done (``calibration.pedal_map``: its
method, its rejections, its verdict). The map's grid is the vehicle file's
``[pedal_sweep]``, the coasting 0 % level added to both pedals.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from appliance.config import parts
from appliance.config.calibration_pedals import PedalMapTable, PedalsCalibration
from appliance.config.pedal_models import PedalSweepSettings
from appliance.maneuvers.merge import StepResult
from appliance.maneuvers.report import FitReport, item_record
from appliance.maneuvers.runner import Progress
from appliance.maneuvers.steps import DrivenStep, bar, sample_number, sample_speed, tail_lines
from calibration.pedal_map import PedalMapAccumulator, PedalMapParams, PedalMapResult
from calibration.pedal_map_cells import PedalMap

SWEEP_PHASES = frozenset({"throttle", "boost", "descend", "coast", "brake"})
STANDING_MPS = 0.1


def map_params(sweep: PedalSweepSettings) -> PedalMapParams:
    """The fit's grid from the vehicle file's ``[pedal_sweep]``: its levels and 0 %
    (coasting, in both maps), its bands, its actuators' settling."""
    return PedalMapParams(
        throttle_levels_pct=(0.0, *sweep.throttle_levels_pct),
        brake_levels_pct=(0.0, *(b for b in sweep.brake_levels_pct if b > 0.0)),
        speed_band_edges_mps=sweep.speed_band_edges_mps,
        traction_settle_s=sweep.traction_settle_s,
        brake_settle_s=sweep.brake_settle_s,
        min_levels_per_band=sweep.min_levels_per_band,
    )


class PedalsStep(DrivenStep):
    name = "pedals"
    summary = "Throttle and brake sweeps, driven by the daemon: the pedal maps."
    # Six to eight minutes of driving, and the turns between stretches of road.
    default_timeout_s = 3600.0
    needed_inputs: tuple[str, ...] = ("board.throttle", "board.brake")
    instructions: tuple[str, ...] = (
        "pedals: on a long straight level road (up to about 1.2 km for the Husky's sweep,",
        "  in as many stretches as you like: each run starts standing), the",
        "  vehicle standing in READY. After the countdown the sweep is armed: press ENGAGE,",
        "  then SPEED + (hold ENGAGE throughout where the vehicle uses hold-to-move). The",
        "  daemon then drives: each run throttle up to the top speed, a coast, a brake to a",
        "  stop. A brake tap, the wheel or OVERRIDE stop it at once; engage and SPEED + again",
        "  to resume (the run starts over). At the end the daemon stops and holds the",
        "  vehicle in speed hold at 0 m/s: OVERRIDE (or a brake tap) takes it back.",
    )

    def reset(self) -> None:
        self.accumulator = PedalMapAccumulator(map_params(self.context.config.pedal_sweep))
        self._phase: str | None = None
        self._run = 0
        self._runs = parts.pedal_sweep_params(self.context.config).runs
        self._done = False
        self._speed_mps: float | None = None

    def preconditions(self, status: Mapping[str, Any]) -> list[str]:
        problems = super().preconditions(status)
        config = self.context.config
        if config.speed_path != "pedals":
            problems.append(
                'the pedal sweep needs speed_path = "pedals" (this vehicle\'s PC104 closes '
                "its own speed loop)"
            )
        speed = status.get("measured_speed_mps")
        if not isinstance(speed, int | float):
            problems.append("no measured speed: is the GNSS/INS receiver fixed?")
        elif abs(speed) > STANDING_MPS:
            problems.append(f"the vehicle is moving ({abs(speed):.2f} m/s): stop first")
        return problems

    def take(self, sample: Mapping[str, Any]) -> str | None:
        phase = sample.get("sweep_phase")
        if phase is None:
            return "the daemon is not running the pedal sweep (it restarted?): resume the run"
        self._phase = str(phase)
        run = sample.get("sweep_run")
        self._run = int(run) if isinstance(run, int) else self._run
        self._done = self._phase == "done"
        speed = sample_speed(sample)
        self._speed_mps = speed
        if sample.get("mode") != "speed_hold" or self._phase not in SWEEP_PHASES:
            return None  # the pedals were not the sweep's: a gap the fit starts over after
        t_s = sample_number(sample, "t_s")
        throttle = sample_number(sample, "throttle_actuator_pct")
        brake = sample_number(sample, "brake_actuator_pct")
        if t_s is not None and speed is not None and throttle is not None and brake is not None:
            self.accumulator.update(t_s, speed, throttle, brake)
        return None

    def progress(self) -> Progress:
        coverage = self.accumulator.coverage()
        fraction = 1.0 if self._done else self._run / self._runs
        return Progress(
            fraction,
            bar(fraction),
            f"run {min(self._run + 1, self._runs)}/{self._runs} {self._phase or 'armed'}; "
            f"cells throttle {coverage.throttle_cells_full}/{coverage.throttle_counts.size}, "
            f"brake {coverage.brake_cells_full}/{coverage.brake_counts.size}",
        )

    def start_step(self) -> str:
        """A resumed run goes on from the first run its samples did not finish (the
        daemon's sweep counts finished runs in each sample)."""
        return f"pedals@{self._run}" if 0 < self._run < self._runs else "pedals"

    def complete(self) -> bool:
        return self._done and self._speed_mps is not None and abs(self._speed_mps) < STANDING_MPS

    def fit(self, samples: Sequence[Mapping[str, Any]], raw_data: str | None) -> FitReport:
        self.reset()
        for sample in samples:
            self.take(sample)
        return pedals_report(self.accumulator.fit(), len(samples), raw_data)


def map_table(pedal_map: PedalMap) -> PedalMapTable:
    """The calibration file's form of a fitted map: per band, its contiguous levels."""
    firsts, rows = [], []
    for band in range(pedal_map.accel_mps2.shape[1]):
        column = pedal_map.accel_mps2[:, band]
        known = np.flatnonzero(np.isfinite(column))
        first = int(known[0]) if known.size else 0
        last = int(known[-1]) + 1 if known.size else 0
        firsts.append(first)
        rows.append(tuple(float(a) for a in column[first:last]))
    return PedalMapTable(
        pedal_pct=tuple(float(p) for p in pedal_map.pedal_pct),
        speed_mps=tuple(float(v) for v in pedal_map.speed_mps),
        first_level_by_band=tuple(firsts),
        accel_mps2_by_band=tuple(rows),
    )


def _map_lines(name: str, pedal_map: PedalMap) -> list[str]:
    header = "  ".join(f"{v:5.2f}" for v in pedal_map.speed_mps)
    lines = [f"  {name} (m/s² at band centre, m/s: {header})"]
    for level, row in zip(pedal_map.pedal_pct, pedal_map.accel_mps2, strict=True):
        cells = "  ".join("   --" if not np.isfinite(a) else f"{a:+5.2f}" for a in row)
        lines.append(f"    {level:5.1f} %  {cells}")
    return lines


def pedals_report(result: PedalMapResult, taken: int, raw_data: str | None) -> FitReport:
    verdict = result.verdict
    measured = int(result.throttle.measured.sum() + result.brake.measured.sum())
    lines = [
        f"pedal maps: {measured} cells measured, residual rms {result.residual_rms_mps2:.3f} "
        f"m/s² (max {result.residual_max_mps2:.3f}), monotonic adjustment throttle "
        f"{result.throttle.monotonic_adjustment_max_mps2:.3f}, brake "
        f"{result.brake.monotonic_adjustment_max_mps2:.3f} m/s²",
        *_map_lines("throttle", result.throttle),
        *_map_lines("brake", result.brake),
        *tail_lines(taken, result.accepted, result.rejected, result.method, verdict),
    ]
    step_result = None
    if verdict.accepted:
        pedals = PedalsCalibration(
            throttle=map_table(result.throttle), brake=map_table(result.brake)
        )
        record = item_record(
            method=result.method,
            accepted=True,
            residual_rms=result.residual_rms_mps2,
            residual_max=result.residual_max_mps2,
            residual_unit="m/s^2",
            samples_used=result.accepted,
            rejected=dict(result.rejected),
            summary=lines[0],
            raw_data=raw_data,
        )
        step_result = StepResult("pedals", {"pedals": pedals.model_dump()}, record)
    return FitReport(
        step="pedals",
        accepted=step_result is not None,
        lines=tuple(lines),
        reasons=verdict.reasons,
        result=step_result,
        draw=lambda plt: _draw_pedals(plt, result),
        figures={
            "cells_measured": measured,
            "residual_rms_mps2": result.residual_rms_mps2,
            "throttle_accel_mps2": _json_cells(result.throttle),
            "brake_accel_mps2": _json_cells(result.brake),
        },
    )


def _json_cells(pedal_map: PedalMap) -> list[list[float | None]]:
    """The map for --json: JSON has no NaN, an unmeasured cell is null."""
    return [[float(a) if np.isfinite(a) else None for a in row] for row in pedal_map.accel_mps2]


def _draw_pedals(plt: Any, result: PedalMapResult) -> Any:
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, name, pedal_map in (
        (axes[0], "throttle", result.throttle),
        (axes[1], "brake", result.brake),
    ):
        for band, speed in enumerate(pedal_map.speed_mps):
            column = pedal_map.accel_mps2[:, band]
            line = ax.plot(pedal_map.pedal_pct, column, "-", label=f"{speed:.1f} m/s")[0]
            shown = pedal_map.measured[:, band]
            ax.plot(pedal_map.pedal_pct[shown], column[shown], "o", color=line.get_color())
        ax.set_xlabel(f"{name} (%)")
        ax.set_ylabel("acceleration (m/s²)")
        ax.set_title(f"{name} map (dots measured, lines between)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    figure.tight_layout()
    return figure
