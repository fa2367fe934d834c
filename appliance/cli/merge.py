"""`dbw merge VEHICLE_MAP WORKER_MAP --t0 X,Y,THETA_DEG`: a worker's map merged into the
vehicle's through their pallets (Kinouchi et al., section 2.2).

Either map is a JSON list of object poses (`appliance.mapping.object_file`) or a PLY
point cloud (`appliance.mapping.cloud_file`), told apart by their first bytes; a cloud's
pallets are found through its proximity points (`appliance.mapping.cloud_pallets`), from
the viewpoints its ``comment dbw origin`` lines give, else from its origin at the
terminal's height (``--origin-height-m``). ``--t0`` is the floor marker's estimate of the
worker map's origin in the vehicle map (x, y in metres, heading in degrees). Printed: the
fitted T (the paper's: vehicle coordinates into the worker's), each pair's residuals,
the pairs the consensus rejected, and the merged map, each added pallet with its
reference area; ``--out`` writes the merged map as an object list the `pallet` source
reads, ``--png`` draws it like the paper's Fig. 9.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import click

from appliance.cli.common import bad_input, draw_png

if TYPE_CHECKING:
    from appliance.mapping.map_file import MapRead
    from appliance.mapping.merge import MergeResult
    from appliance.mapping.pallets import Pallet, PalletMap


def _t0(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(map(math.isfinite, values)):
        raise click.BadParameter(f"{text!r}: give X,Y,THETA_DEG as three finite numbers")
    return values[0], values[1], values[2]


def read_map(
    path: str,
    frame: str,
    origin_height_m: float,
    details: list[str],
    with_alternatives: bool = False,
) -> MapRead:
    """The pallet map of a file (an object list, or a cloud's detected pallets, with the
    faces' alternative readings if asked), or exit 2 naming what is wrong with it."""
    from appliance.mapping.map_file import MapFileError, read_pallet_map

    try:
        read = read_pallet_map(path, frame, origin_height_m, with_alternatives)
    except MapFileError as exc:
        bad_input(str(exc))
    details.extend(read.notes)
    return read


def _pallet_json(pallet: Pallet) -> dict[str, Any]:
    sigma = [math.sqrt(max(float(pallet.covariance[i, i]), 0.0)) for i in range(3)]
    return {
        "name": pallet.name,
        "kind": pallet.kind.value,
        "x_m": round(pallet.x_m, 6),
        "y_m": round(pallet.y_m, 6),
        "yaw_deg": round(math.degrees(pallet.yaw_rad), 5),
        "sigma_x_m": round(sigma[0], 6),
        "sigma_y_m": round(sigma[1], 6),
        "sigma_yaw_deg": round(math.degrees(sigma[2]), 5),
        "covariance": [[float(v) for v in row] for row in pallet.covariance],
    }


def result_json(result: MergeResult, vehicle: PalletMap, worker: PalletMap) -> dict[str, Any]:
    fit = result.fit
    t = fit.vehicle_in_worker
    inverse = fit.worker_in_vehicle
    sigmas = [math.sqrt(max(float(fit.covariance[i, i]), 0.0)) for i in range(3)]
    pairs = []
    for (v, w), position, posture in zip(
        result.robust.inliers, fit.position_residuals_m, fit.posture_residuals_rad, strict=True
    ):
        pairs.append(
            {
                "vehicle": vehicle.pallets[v].name or v,
                "worker": worker.pallets[w].name or w,
                "position_residual_m": round(float(position), 6),
                "posture_residual_deg": round(math.degrees(float(posture)), 5),
            }
        )
    rejected = [
        {
            "vehicle": vehicle.pallets[r.vehicle_index].name or r.vehicle_index,
            "worker": worker.pallets[r.worker_index].name or r.worker_index,
            "position_residual_m": round(r.position_residual_m, 6),
            "posture_residual_deg": round(math.degrees(r.posture_residual_rad), 5),
        }
        for r in result.robust.rejected
    ]
    merged = []
    for entry in result.pallets:
        item = _pallet_json(entry.pallet)
        item["from"] = "worker" if entry.from_worker else "vehicle"
        if entry.reference_area is not None:
            area = entry.reference_area
            item["reference_area"] = {
                "x_m": round(area.centre_x_m, 6),
                "y_m": round(area.centre_y_m, 6),
                "radius_m": round(area.radius_m, 6),
            }
        merged.append(item)
    return {
        "kind": "merge",
        "T": {"x_m": t.x_m, "y_m": t.y_m, "theta_deg": math.degrees(t.yaw_rad)},
        "worker_in_vehicle": {
            "x_m": inverse.x_m,
            "y_m": inverse.y_m,
            "theta_deg": math.degrees(inverse.yaw_rad),
        },
        "sigma": {"x_m": sigmas[0], "y_m": sigmas[1], "theta_deg": math.degrees(sigmas[2])},
        "cost": fit.cost,
        "pairs": pairs,
        "rejected_pairs": rejected,
        "merged": merged,
        "added": sum(1 for p in result.pallets if p.from_worker),
    }


def merged_object_list(result: MergeResult, frame: str) -> str:
    """The merged map as an object file (`appliance.mapping.object_file`) with each
    pallet's full covariance and who saw it: what the `pallet` source reads."""
    objects = []
    for index, entry in enumerate(result.pallets):
        pallet = entry.pallet
        objects.append(
            {
                "name": pallet.name or f"pallet_{index}",
                "kind": pallet.kind.value,
                "x_m": pallet.x_m,
                "y_m": pallet.y_m,
                "yaw_deg": math.degrees(pallet.yaw_rad),
                "covariance_m_rad": [[float(v) for v in row] for row in pallet.covariance],
                "seen_by": "worker" if entry.from_worker else "vehicle",
            }
        )
    return json.dumps({"frame": frame, "objects": objects}, indent=1) + "\n"


def _draw(plt: Any, result: MergeResult, worker: PalletMap) -> Any:
    """The paper's Fig. 9: the vehicle's pallets, the worker's moved by the fit, the added
    ones with their reference areas."""
    from appliance.mapping.merge import move_worker_pallet

    figure, axes = plt.subplots(figsize=(8, 8))
    for entry in result.pallets:
        corners = entry.pallet.corners_xy_m()
        xs = [c[0] for c in corners] + [corners[0][0]]
        ys = [c[1] for c in corners] + [corners[0][1]]
        if entry.from_worker:
            axes.plot(xs, ys, color="tab:green", linewidth=2)
            area = entry.reference_area
            if area is not None:
                axes.add_patch(
                    plt.Circle(
                        (area.centre_x_m, area.centre_y_m),
                        area.radius_m,
                        fill=False,
                        linestyle="--",
                        color="tab:green",
                    )
                )
        else:
            axes.plot(xs, ys, color="tab:blue", linewidth=2)
        axes.annotate(entry.pallet.name, (entry.pallet.x_m, entry.pallet.y_m), fontsize=7)
    for pallet in worker.pallets:
        moved = move_worker_pallet(pallet, result.fit)
        corners = moved.corners_xy_m()
        xs = [c[0] for c in corners] + [corners[0][0]]
        ys = [c[1] for c in corners] + [corners[0][1]]
        axes.plot(xs, ys, color="tab:orange", linewidth=0.8, linestyle=":")
    axes.plot([], [], color="tab:blue", label="vehicle's pallets")
    axes.plot([], [], color="tab:orange", linestyle=":", label="worker's, moved by T")
    axes.plot([], [], color="tab:green", label="added, with reference area")
    axes.set_aspect("equal")
    axes.set_xlabel("x (m, vehicle map)")
    axes.set_ylabel("y (m)")
    axes.legend(loc="best", fontsize=8)
    axes.set_title("merged map")
    return figure


@click.command()
@click.argument("vehicle_map", type=click.Path(dir_okay=False))
@click.argument("worker_map", type=click.Path(dir_okay=False))
@click.option(
    "--t0",
    "t0_text",
    required=True,
    metavar="X,Y,THETA_DEG",
    help="The floor marker's estimate of the worker map's origin in the vehicle map.",
)
@click.option(
    "--w",
    "w_m2_per_rad2",
    type=click.FloatRange(min=0.0, max=1e6),
    default=None,
    help="Weight of posture against position in the fit, m^2/rad^2 (eq. 1's w). "
    "Default: (20 mm / 1 deg)^2, a consumer terminal's.",
)
@click.option(
    "--origin-height-m",
    type=click.FloatRange(min=0.0, max=5.0),
    default=1.2,
    help="Where a cloud without viewpoints was scanned from: its origin at this height.",
)
@click.option("--out", "out_file", metavar="FILE.json", help="Write the merged map here.")
@click.option("--png", "png_file", metavar="OUT.png", help="Draw the merged map (Fig. 9).")
@click.option("--json", "as_json", is_flag=True, help="One JSON object.")
def merge(
    vehicle_map: str,
    worker_map: str,
    t0_text: str,
    w_m2_per_rad2: float | None,
    origin_height_m: float,
    out_file: str | None,
    png_file: str | None,
    as_json: bool,
) -> None:
    """Merge WORKER_MAP into VEHICLE_MAP through their pallets (JSON object lists or PLY)."""
    from appliance.config.atomic import write_text_atomic
    from appliance.mapping.merge import MergeParams, MergeRefusal, merge_maps
    from appliance.mapping.pallets import PalletMap
    from drivers.geometry import Pose2D

    x_m, y_m, theta_deg = _t0(t0_text)
    details: list[str] = []
    vehicle = read_map(vehicle_map, "vehicle", origin_height_m, details).pallet_map
    read = read_map(worker_map, "worker", origin_height_m, details, with_alternatives=True)
    alternatives = read.alternatives
    params = MergeParams()
    if w_m2_per_rad2 is not None:
        params = replace(params, robust=replace(params.robust, w_m2_per_rad2=w_m2_per_rad2))
    t0 = Pose2D(x_m, y_m, math.radians(theta_deg))
    result = merge_maps(vehicle, read.pallet_map, t0, params, alternatives)
    # The pairs' worker indices run on into the alternatives (unnamed: shown by index).
    worker = PalletMap(read.pallet_map.pallets + alternatives, "worker", worker_map)
    for line in details:
        click.echo(f"warning: {line}", err=True)
    if isinstance(result, MergeRefusal):
        message = (
            f"not merged: {result.reason} "
            f"(vehicle map {len(vehicle)} pallets, worker map {len(read.pallet_map)})"
        )
        if as_json:
            click.echo(json.dumps({"kind": "merge", "merged": False, "reason": result.reason}))
        click.echo(message, err=True)
        raise SystemExit(1)
    if out_file is not None:
        try:
            write_text_atomic(out_file, merged_object_list(result, vehicle.frame))
        except OSError as exc:
            bad_input(f"{out_file}: cannot write it: {exc.strerror or exc}")
    report = result_json(result, vehicle, worker)
    if png_file is not None:
        problem = draw_png(png_file, lambda plt: _draw(plt, result, read.pallet_map))
        if problem is not None:
            click.echo(f"{png_file}: {problem}", err=True)
    if as_json:
        click.echo(json.dumps(report))
        return
    _print_report(report, len(vehicle), len(read.pallet_map))


def _print_report(report: dict[str, Any], vehicle_count: int, worker_count: int) -> None:
    t, sigma = report["T"], report["sigma"]
    click.echo(
        f"T (vehicle into worker): x {t['x_m']:+.4f} m, y {t['y_m']:+.4f} m, "
        f"theta {t['theta_deg']:+.4f} deg  (sigma {sigma['x_m'] * 1e3:.1f} mm, "
        f"{sigma['y_m'] * 1e3:.1f} mm, {sigma['theta_deg']:.3f} deg)"
    )
    click.echo(
        f"pairs: {len(report['pairs'])} of {vehicle_count} vehicle and {worker_count} "
        f"worker pallets"
    )
    for pair in report["pairs"]:
        click.echo(
            f"  {pair['vehicle']} ~ {pair['worker']}: {pair['position_residual_m'] * 1e3:.1f} mm,"
            f" {pair['posture_residual_deg']:+.2f} deg"
        )
    for pair in report["rejected_pairs"]:
        click.echo(
            f"  rejected {pair['vehicle']} ~ {pair['worker']}: "
            f"{pair['position_residual_m'] * 1e3:.1f} mm, {pair['posture_residual_deg']:+.2f} deg"
        )
    click.echo(f"merged map: {len(report['merged'])} pallets, {report['added']} added")
    for item in report["merged"]:
        area = item.get("reference_area")
        where = f" reference area r={area['radius_m']:.3f} m" if area else ""
        click.echo(
            f"  {item['from']:7s} {item['name'] or '-':16s} {item['kind']:9s} "
            f"x {item['x_m']:+8.3f} y {item['y_m']:+8.3f} yaw {item['yaw_deg']:+8.2f} deg{where}"
        )
