"""`dbw sim survey`: a simulated worker's map of a site, as a worker's terminal hands it over.

Kinouchi et al.'s worker photographs the floor marker, then walks the storage area with a
consumer 3D LiDAR (``appliance.sim.worker_terminal``). Written: the 3D cloud as PLY
(with the viewpoints as ``comment dbw origin`` lines), or with ``--objects`` the pallets
the terminal found as an object list. Printed: the T0 to give `dbw merge` (the marker's
surveyed pose: what the vehicle believes the worker map's origin is) and, for judging, the
true pose of the worker map in the site.
"""

from __future__ import annotations

import json
import math

import click

from appliance.cli.common import bad_input

ERRORS = ("consumer", "worse", "ideal")


def _pose(text: str) -> tuple[float, float, float]:
    try:
        values = [float(p) for p in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(map(math.isfinite, values)):
        raise click.BadParameter(f"{text!r}: give X,Y,THETA_DEG as three finite numbers")
    return values[0], values[1], values[2]


@click.command()
@click.option("--site", "site_name", default="pallets", show_default=True, help="Site or file.")
@click.option("--seed", type=click.IntRange(min=0), default=1, show_default=True)
@click.option(
    "--errors",
    "error_name",
    type=click.Choice(ERRORS),
    default="consumer",
    show_default=True,
    help="The terminal's errors: a consumer device's, 2.5 times worse (the paper's n = 2), none.",
)
@click.option(
    "--marker",
    "marker_text",
    default="0,0,0",
    show_default=True,
    metavar="X,Y,THETA_DEG",
    help="Where the floor marker is in the site (the worker map's origin).",
)
@click.option("--objects", is_flag=True, help="Write the pallets found (an object list), no cloud.")
@click.option("--ascii", "as_ascii", is_flag=True, help="An ascii PLY instead of binary.")
@click.option("--out", "out_file", required=True, metavar="FILE", help="Where to write the map.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
def survey(
    site_name: str,
    seed: int,
    error_name: str,
    marker_text: str,
    objects: bool,
    as_ascii: bool,
    out_file: str,
    as_json: bool,
) -> None:
    """A simulated worker's terminal map of the site, written to --out."""
    import numpy as np

    from appliance.config import ConfigError
    from appliance.mapping.cloud_file import write_ply
    from appliance.mapping.object_file import dump_object_map
    from appliance.sim.site_file import load_site
    from appliance.sim.terminal_errors import CONSUMER, IDEAL, WORSE
    from appliance.sim.worker_route import walk_around
    from appliance.sim.worker_terminal import object_pallet_map, survey_objects
    from appliance.sim.worker_terminal import survey as run_survey
    from drivers.geometry import Pose2D

    try:
        site = load_site(site_name)
    except ConfigError as exc:
        bad_input(exc.render())
    if not site.pallets:
        bad_input(f"site {site_name!r} has no pallets to survey")
    x_m, y_m, theta_deg = _pose(marker_text)
    marker = Pose2D(x_m, y_m, math.radians(theta_deg))
    errors = {"consumer": CONSUMER, "worse": WORSE, "ideal": IDEAL}[error_name]
    rng = np.random.default_rng(seed)
    viewpoints = walk_around(site)
    if objects:
        found = survey_objects(site, marker, errors, rng, viewpoints=viewpoints)
        listed = object_pallet_map(found.objects)
        data = dump_object_map(listed)
        t0_true, count = found.t0_true, len(listed)
    else:
        cloud = run_survey(site, marker, viewpoints, rng=rng, errors=errors)
        data = write_ply(
            cloud.xyz_m,
            binary=not as_ascii,
            comments=[f"dbw sim survey of {site.name}, seed {seed}, errors {error_name}"],
            origins_m=[tuple(o) for o in cloud.origins_m],
        )
        t0_true, count = cloud.t0_true, int(cloud.xyz_m.shape[0])
    try:
        with open(out_file, "wb") as handle:
            handle.write(data)
    except OSError as exc:
        bad_input(f"{out_file}: cannot write it: {exc.strerror or exc}")
    report = {
        "kind": "survey",
        "file": out_file,
        "form": "objects" if objects else "cloud",
        "count": count,
        "viewpoints": len(viewpoints),
        "t0": f"{marker.x_m:g},{marker.y_m:g},{math.degrees(marker.yaw_rad):g}",
        "worker_in_site_true": {
            "x_m": t0_true.x_m,
            "y_m": t0_true.y_m,
            "theta_deg": math.degrees(t0_true.yaw_rad),
        },
    }
    if as_json:
        click.echo(json.dumps(report))
        return
    what = "pallets" if objects else "points"
    click.echo(f"{out_file}: {count} {what} from {len(viewpoints)} viewpoints ({error_name})")
    click.echo(f"merge with: dbw merge VEHICLE_MAP {out_file} --t0 {report['t0']}")
    click.echo(
        f"(the worker map's true origin in the site: x {t0_true.x_m:+.4f} m, "
        f"y {t0_true.y_m:+.4f} m, theta {math.degrees(t0_true.yaw_rad):+.4f} deg)"
    )
