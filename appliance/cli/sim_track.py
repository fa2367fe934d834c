"""`dbw sim track`: follow a course with the route autopilot on the simulated Husky.

The daemon's route chain (``appliance.guidance.route_follow``: fixes, the varying
local/global frame, planner, pure pursuit, speed profile) and the ``pedals`` speed
controller against the simulated vehicle (``appliance.sim.track_run``), judged by the
truth: the cross-track error at the anchor after the first metres, the time and distance
to converge below 0.1 m, the steering rate used, the speed error. Exit status 0 when the
course was driven to its end, 1 when the autopilot stopped early or the course is one the
vehicle cannot drive (said where), 2 for bad input.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import click
import numpy as np

from appliance.cli.common import load_or_exit
from appliance.config.models import VehicleConfig
from appliance.routes.check import check_route, min_turn_radius_m
from appliance.routes.geojson import RouteFileError, read_route_file
from appliance.sim.courses import (
    CourseError,
    FloatArray,
    arc_course,
    checked_course,
    load_course_csv,
    off_road_course,
    straight_course,
)
from appliance.sim.track_run import TrackResult, TrackRunParams, run_track

BUILTIN_COURSES = "builtin:straight, builtin:arc15, builtin:offroad[:SEED]"


def load_course(spec: str) -> FloatArray:
    """A course file (x_m,y_m lines, or a GeoJSON route) or a built-in course."""
    if spec.startswith("builtin:"):
        name, _, seed = spec.removeprefix("builtin:").partition(":")
        if name == "straight":
            return straight_course(300.0)
        if name == "arc15":
            return arc_course(15.0, arc_deg=180.0, transition_m=10.0)
        if name == "offroad":
            try:
                return off_road_course(int(seed) if seed else 1)
            except ValueError:
                raise CourseError(f"{spec}: the seed must be a whole number") from None
        raise CourseError(f"{spec}: no such built-in course (known: {BUILTIN_COURSES})")
    path = Path(spec)
    if path.suffix.lower() in (".geojson", ".json"):
        try:
            route = read_route_file(path)
        except RouteFileError as exc:
            raise CourseError(str(exc)) from None
        return checked_course(np.asarray(route.own_points_m, dtype=np.float64), spec)
    return load_course_csv(path)


def course_problems(config: VehicleConfig, course: FloatArray) -> list[str]:
    """Why the vehicle cannot drive the course (empty: it can): turns tighter than it
    turns, each named where."""
    report = check_route(course, min_turn_radius_m(config))
    return [p.message for p in report.problems if p.severity.value == "refused"]


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None or not math.isfinite(value) else round(value, digits)


def result_document(result: TrackResult, params: TrackRunParams) -> dict[str, object]:
    return {
        "completed": result.reason == "end of course",
        "reason": result.reason,
        "course_length_m": round(result.course_length_m, 1),
        "distance_m": round(result.distance_m, 1),
        "rms_cross_track_m": _round(result.rms_cross_track_m, 4),
        "max_cross_track_m": _round(result.max_cross_track_m, 4),
        "converge_time_s": _round(result.converge_time_s, 2),
        "converge_distance_m": _round(result.converge_distance_m, 2),
        "max_steer_rate_deg_per_s": round(result.max_steer_rate_deg_per_s, 2),
        "rms_speed_error_mps": _round(result.rms_speed_error_mps, 4),
        "rms_speed_error_vs_set_mps": _round(result.rms_speed_error_vs_set_mps, 4),
        "mean_speed_mps": round(result.mean_speed_mps, 3),
        "time_s": round(result.duration_s, 2),
        "wall_time_s": round(result.wall_s, 3),
        "real_time_factor": round(result.realtime_factor, 1),
        "jumps_followed": result.jumps_followed,
        "settle_m": params.settle_m,
        "speed_mps": params.speed_mps,
        "offset_m": params.offset_m,
        "loc_noise_m": params.loc_noise_m,
        "loc_jump_m": params.loc_jump_m,
        "loc_jump_period_s": params.loc_jump_period_s,
        "tracker": params.tracker,
        "seed": params.seed,
    }


@click.command()
@click.option(
    "--course",
    "course_spec",
    metavar="FILE|BUILTIN",
    required=True,
    help=f"x_m,y_m lines, a GeoJSON route, or one of {BUILTIN_COURSES}.",
)
@click.option(
    "--profile", "config_name", metavar="FILE|PROFILE", default="husky", show_default=True
)
@click.option("--speed-mps", type=click.FloatRange(0.1, 20.0), default=4.47, show_default=True)
@click.option(
    "--offset-m",
    type=click.FloatRange(-10.0, 10.0),
    default=0.0,
    show_default=True,
    help="Start this far left of the course (negative: right).",
)
@click.option("--loc-noise-m", type=click.FloatRange(0.0, 1.0), default=0.05, show_default=True)
@click.option("--loc-jump-m", type=click.FloatRange(0.0, 5.0), default=0.0, show_default=True)
@click.option(
    "--loc-jump-period-s", type=click.FloatRange(1.0, 3600.0), default=20.0, show_default=True
)
@click.option(
    "--tracker",
    type=click.Choice(["4ws", "plain"]),
    default="4ws",
    show_default=True,
    help="4ws: the counter-steer pure pursuit with its anchor; plain: eq. 1 from the rear "
    "axle, no k, for comparison.",
)
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=1, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def track(
    course_spec: str,
    config_name: str,
    speed_mps: float,
    offset_m: float,
    loc_noise_m: float,
    loc_jump_m: float,
    loc_jump_period_s: float,
    tracker: str,
    seed: int,
    as_json: bool,
) -> None:
    """Drive a course with the route autopilot on the simulated vehicle; report the errors."""
    config = load_or_exit(config_name)
    try:
        course = load_course(course_spec)
    except CourseError as exc:
        click.echo(f"dbw sim track: {exc}", err=True)
        sys.exit(2)
    problems = course_problems(config, course)
    if problems:
        click.echo(f"dbw sim track: {config.name} cannot drive {course_spec}:", err=True)
        for problem in problems:
            click.echo(f"  {problem}", err=True)
        sys.exit(1)
    params = TrackRunParams(
        speed_mps=speed_mps,
        offset_m=offset_m,
        loc_noise_m=loc_noise_m,
        loc_jump_m=loc_jump_m,
        loc_jump_period_s=loc_jump_period_s,
        tracker="plain" if tracker == "plain" else "4ws",
        seed=seed,
    )
    result = run_track(config, course, params)
    document = result_document(result, params)
    if as_json:
        click.echo(json.dumps(document))
    else:
        click.echo(f"{'COMPLETED' if document['completed'] else 'STOPPED'}: {result.reason}")
        click.echo(
            f"  cross-track at the anchor after {params.settle_m:.0f} m: RMS "
            f"{result.rms_cross_track_m * 100:.1f} cm, max {result.max_cross_track_m * 100:.1f} cm"
        )
        converge = (
            "never below 0.1 m"
            if result.converge_distance_m is None
            else f"below 0.1 m after {result.converge_distance_m:.1f} m "
            f"({result.converge_time_s:.1f} s)"
        )
        click.echo(f"  {converge}; steering rate up to {result.max_steer_rate_deg_per_s:.1f} deg/s")
        click.echo(
            f"  speed error RMS {result.rms_speed_error_mps:.3f} m/s against the target, "
            f"{result.rms_speed_error_vs_set_mps:.3f} m/s against the set speed"
        )
        click.echo(
            f"  {result.distance_m:.0f} of {result.course_length_m:.0f} m, "
            f"{result.duration_s:.0f} s simulated in {result.wall_s:.1f} s "
            f"({result.realtime_factor:.0f}x real time)"
        )
    sys.exit(0 if document["completed"] else 1)
