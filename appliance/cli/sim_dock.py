"""`dbw sim dock`: one docking approach on the simulated flat-bed, faster than real time.

The daemon's own perception, localizer and docking controller against the simulated world
(``appliance.sim.dock_run``), judged by the truth: the teeth's lateral offsets in their
troughs, the heading, the gap, the pattern switches, and whether a tooth reached a trough
misaligned. Exit status 0 when docked within the troughs, 1 when not, 2 for a bad vehicle.
"""

from __future__ import annotations

import json
import math
import os
import sys

import click

from appliance.cli.common import load_or_exit
from appliance.config.models import VehicleKind
from appliance.sim.dock_run import DockResult, DockRunParams, run_dock, scan_latency_s


def _usable_cores() -> int:
    """The cores this process may run on (a container's or `taskset`'s share, not the
    host's count where the platform says)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _finite_or_none(value: float, digits: int) -> float | None:
    return round(value, digits) if math.isfinite(value) else None


def result_document(
    result: DockResult, params: DockRunParams, latency_s: float
) -> dict[str, object]:
    return {
        "success": result.success,
        "reason": result.reason,
        "teeth_lateral_mm": [round(t * 1000.0, 3) for t in result.teeth_lateral_m],
        "lateral_error_mm": round(max(abs(t) for t in result.teeth_lateral_m) * 1000.0, 3),
        "heading_error_deg": round(result.heading_error_deg, 4),
        "gap_mm": round(result.gap_m * 1000.0, 2),
        "pattern_switches": result.pattern_switches,
        "attempts": result.attempts,
        "contact_misaligned": result.contact_misaligned,
        "final_speed_mps": round(result.final_speed_mps, 4),
        "time_s": round(result.sim_time_s, 2),
        "wall_time_s": round(result.wall_time_s, 3),
        "real_time_factor": round(result.real_time_factor, 2),
        "estimate_error_mm": None
        if math.isnan(result.estimate_error_m)
        else round(result.estimate_error_m * 1000.0, 2),
        "rejected_measurements": result.rejected,
        "mean_nees": _finite_or_none(result.mean_nees, 3),
        "mean_nees_near": _finite_or_none(result.mean_nees_near, 3),
        "start": {
            "x_m": -params.start_gap_m,
            "y_m": params.start_y_m,
            "heading_deg": params.start_heading_deg,
        },
        "seed": params.seed,
        "scanner": "ideal" if params.ideal_scanner else "realistic",
        "calibrated": params.calibrated,
        "scan_latency_ms": round(latency_s * 1000.0, 3),
        "scans_rendered": "by a worker" if params.render_worker else "inline",
    }


@click.command()
@click.option(
    "--config", "config_name", metavar="FILE|PROFILE", default="flatbed", show_default=True
)
@click.option(
    "--start-x-m",
    type=click.FloatRange(-15.0, -0.5),
    default=-10.0,
    show_default=True,
    help="Where the front end's centre starts on the launcher's axis (negative: in front).",
)
@click.option("--start-y-m", type=click.FloatRange(-3.0, 3.0), default=0.0, show_default=True)
@click.option(
    "--start-heading-deg", type=click.FloatRange(-15.0, 15.0), default=0.0, show_default=True
)
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=1, show_default=True)
@click.option("--ideal-scanner", is_flag=True, help="Scanners without any error.")
@click.option(
    "--uncalibrated",
    is_flag=True,
    help="The localizer knows only the configured mounts, not each scanner's true mount "
    "and range offset (what `dbw calibrate scanners` finds).",
)
@click.option("--timeout-s", type=click.FloatRange(min=1.0), default=300.0, show_default=True)
@click.option(
    "--one-core",
    is_flag=True,
    help="Render the scans in this process too (by default, on a machine of two or more "
    "cores, a forked worker renders them while this process localizes: the same run).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def dock(
    config_name: str,
    start_x_m: float,
    start_y_m: float,
    start_heading_deg: float,
    seed: int,
    ideal_scanner: bool,
    uncalibrated: bool,
    timeout_s: float,
    one_core: bool,
    as_json: bool,
) -> None:
    """Dock the simulated flat-bed to the launcher and report how well the teeth went in."""
    config = load_or_exit(config_name)
    if config.kind is not VehicleKind.FLATBED:
        click.echo(f"{config_name}: docking needs a flat-bed vehicle, not {config.kind}", err=True)
        sys.exit(2)
    params = DockRunParams(
        start_gap_m=-start_x_m,
        start_y_m=start_y_m,
        start_heading_deg=start_heading_deg,
        seed=seed,
        ideal_scanner=ideal_scanner,
        calibrated=not uncalibrated,
        timeout_s=timeout_s,
        render_worker=not one_core and _usable_cores() > 1,
    )
    result = run_dock(config, params)
    document = result_document(result, params, scan_latency_s(config, params))
    if as_json:
        click.echo(json.dumps(document))
    else:
        verdict = "DOCKED" if result.success else "NOT DOCKED"
        click.echo(f"{verdict}: {result.reason}")
        click.echo(
            f"  teeth lateral {document['teeth_lateral_mm']} mm, heading "
            f"{document['heading_error_deg']} deg, gap {document['gap_mm']} mm"
        )
        click.echo(
            f"  {result.pattern_switches} pattern switches, {result.attempts} attempt(s), "
            f"{result.sim_time_s:.1f} s simulated in {result.wall_time_s:.1f} s "
            f"({result.real_time_factor:.1f}x real time)"
        )
    sys.exit(0 if result.success else 1)
