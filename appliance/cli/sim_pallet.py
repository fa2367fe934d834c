"""`dbw sim pallet`: one guidance to a pallet in the simulated forklift's blind area.

The whole flow on the `pallets` site (``appliance.sim.pallet_run``): the worker's 3D map,
the vehicle's own pallets, the merge, the plan, the approach with the pallet detected
again, judged by the truth: the fork tips against the true pallet's face. Trials 1-3 are
the paper's three (trial 2 with the worker's terminal at its worst). Exit status 0 when
the forks stopped at the pallet's openings, 1 when not, 2 for a bad vehicle.
"""

from __future__ import annotations

import json
import math
import sys

import click

from appliance.cli.common import load_or_exit
from appliance.config.models import VehicleKind
from appliance.sim.pallet_run import TRIALS, PalletResult, PalletRunParams, run_pallet


def _num(value: float, scale: float, digits: int) -> float | None:
    return round(value * scale, digits) if math.isfinite(value) else None


def result_document(result: PalletResult) -> dict[str, object]:
    return {
        "success": result.success,
        "reason": result.reason,
        "phase": result.phase,
        "trial": result.trial,
        "seed": result.seed,
        "fork_lateral_error_mm": _num(result.tips_lateral_m, 1e3, 3),
        "fork_angle_error_deg": _num(result.heading_error_deg, 1.0, 4),
        "fork_tips_past_face_mm": _num(result.tips_along_m, 1e3, 3),
        "translation_error_mm": _num(result.translation_error_m, 1e3, 3),
        "merge_error_mm": _num(result.merge_error_m, 1e3, 2),
        "merge_error_deg": _num(result.merge_error_deg, 1.0, 4),
        "worker_pallets": result.worker_pallets,
        "vehicle_pallets": result.vehicle_pallets,
        "plan_length_m": _num(result.plan_length_m, 1.0, 2),
        "entry_face": result.face,
        "time_s": round(result.sim_time_s, 2),
        "wall_time_s": round(result.wall_time_s, 3),
        "real_time_factor": round(result.real_time_factor, 2),
    }


@click.command()
@click.option(
    "--config", "config_name", metavar="FILE|PROFILE", default="forklift-sim", show_default=True
)
@click.option(
    "--trial", type=click.Choice([str(n) for n in TRIALS]), default="1", show_default=True
)
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=1, show_default=True)
@click.option("--timeout-s", type=click.FloatRange(min=10.0), default=400.0, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def pallet(config_name: str, trial: str, seed: int, timeout_s: float, as_json: bool) -> None:
    """Guide the simulated forklift to a pallet it cannot see, through a worker's map."""
    config = load_or_exit(config_name)
    if config.kind is not VehicleKind.FORKLIFT:
        click.echo(f"{config_name}: pallets need a forklift, not {config.kind}", err=True)
        sys.exit(2)
    result = run_pallet(config, PalletRunParams(trial=int(trial), seed=seed, timeout_s=timeout_s))
    document = result_document(result)
    if as_json:
        click.echo(json.dumps(document))
    else:
        verdict = "AT THE PALLET" if result.success else "NOT AT THE PALLET"
        click.echo(f"{verdict}: {result.reason}")
        click.echo(
            f"  fork tips {document['fork_lateral_error_mm']} mm off the axis, "
            f"{document['fork_tips_past_face_mm']} mm past the face, angle "
            f"{document['fork_angle_error_deg']} deg"
        )
        click.echo(
            f"  maps: worker {result.worker_pallets} pallets, vehicle {result.vehicle_pallets}, "
            f"merged within {document['merge_error_mm']} mm and {document['merge_error_deg']} deg"
        )
        click.echo(
            f"  {result.sim_time_s:.1f} s simulated in {result.wall_time_s:.1f} s "
            f"({result.real_time_factor:.1f}x real time)"
        )
    sys.exit(0 if result.success else 1)
