"""Courses for `dbw sim track` and the tracking benchmark: files, and courses made to order.

A course is the path the simulated vehicle is asked to follow, as an (N, 2) array of
east-north metres. On disk it is one ``x_m,y_m`` pair per line (a header line naming the
columns and ``#`` comments allowed), or a route file (GeoJSON, see docs/routes.md) that
the caller converts into its frame.

The made-to-order ones stand for the paper's tuning runs (a straight line, one arc) and
for its off-road course: curvature that keeps changing, with arcs down to 15 m radius,
joined by clothoid transitions (curvature linear in arc length) so that the path itself
has no steering steps a real trail would not have. They are drawn from a seed, so a
figure measured on "the off-road mile, seed 1" can be measured again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

MILE_M = 1609.344
MAX_COURSE_FILE_BYTES = 50 * 1024 * 1024
MAX_COURSE_POINTS = 1_000_000


class CourseError(ValueError):
    """A course file that cannot be used, with where and why."""


def load_course_csv(path: Path) -> FloatArray:
    """Read ``x_m,y_m`` lines; refuse anything else, naming the line."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise CourseError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    if size > MAX_COURSE_FILE_BYTES:
        raise CourseError(f"{path}: {size} bytes, more than a course file may have")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise CourseError(f"{path}: cannot read as UTF-8 text: {exc}") from exc
    points: list[tuple[float, float]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != 2:
            raise CourseError(f"{path}:{number}: expected 'x_m,y_m', got {raw.strip()!r}")
        try:
            x_m, y_m = float(fields[0]), float(fields[1])
        except ValueError:
            if not points and fields[0].lower().startswith("x"):
                continue  # a header naming the columns
            raise CourseError(f"{path}:{number}: not two numbers: {raw.strip()!r}") from None
        if not (math.isfinite(x_m) and math.isfinite(y_m)):
            raise CourseError(f"{path}:{number}: not finite: {raw.strip()!r}")
        points.append((x_m, y_m))
        if len(points) > MAX_COURSE_POINTS:
            raise CourseError(f"{path}: more than {MAX_COURSE_POINTS} points")
    return checked_course(np.asarray(points, dtype=np.float64).reshape(-1, 2), str(path))


def checked_course(points_m: FloatArray, where: str = "course") -> FloatArray:
    """Drop repeated points; a course needs two distinct points and some length."""
    if points_m.ndim != 2 or points_m.shape[1] != 2:
        raise CourseError(f"{where}: points must be an (N, 2) array, got shape {points_m.shape}")
    if not np.all(np.isfinite(points_m)):
        raise CourseError(f"{where}: points must be finite")
    if len(points_m) == 0:
        raise CourseError(f"{where}: no points")
    step_m = np.hypot(*np.diff(points_m, axis=0).T)
    keep = np.concatenate(([True], step_m > 1e-6))
    distinct = points_m[keep]
    if len(distinct) < 2:
        raise CourseError(f"{where}: fewer than two distinct points")
    return distinct


def save_course_csv(path: Path, points_m: FloatArray) -> None:
    lines = ["x_m,y_m"] + [f"{x:.4f},{y:.4f}" for x, y in points_m]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def integrate_curvature(
    segment_curvature_1pm: FloatArray, spacing_m: float, heading_rad: float = 0.0
) -> FloatArray:
    """The points of a path made of ``len(segment_curvature_1pm)`` pieces of ``spacing_m``,
    each an arc of the given curvature: exact for piecewise-constant curvature (each
    piece's chord is ``2 sin(k ds / 2) / k`` long at the mean heading)."""
    kappa = np.asarray(segment_curvature_1pm, dtype=np.float64)
    turn = kappa * spacing_m
    heading = heading_rad + np.concatenate(([0.0], np.cumsum(turn)))
    mid = heading[:-1] + 0.5 * turn
    chord = np.where(
        np.abs(turn) > 1e-12,
        2.0 * np.sin(0.5 * turn) / np.where(np.abs(kappa) > 0, kappa, 1.0),
        spacing_m,
    )
    steps = np.column_stack((np.cos(mid), np.sin(mid))) * chord[:, None]
    points = np.zeros((len(kappa) + 1, 2))
    points[0] = 0.0
    points[1:] = np.cumsum(steps, axis=0)
    return points


def _segment_midpoints(total_m: float, spacing_m: float) -> FloatArray:
    n = max(round(total_m / spacing_m), 1)
    return (np.arange(n, dtype=np.float64) + 0.5) * spacing_m


def straight_course(length_m: float = 200.0, spacing_m: float = 0.5) -> FloatArray:
    n = round(length_m / spacing_m) + 1
    return np.column_stack((np.linspace(0.0, length_m, n), np.zeros(n)))


def arc_course(
    radius_m: float,
    lead_in_m: float = 30.0,
    arc_deg: float = 180.0,
    lead_out_m: float = 30.0,
    spacing_m: float = 0.5,
    left: bool = True,
    transition_m: float = 0.0,
) -> FloatArray:
    """A straight lead-in, an arc (positive radius, to the left unless ``left`` is False)
    and a straight lead-out; with ``transition_m`` the curvature ramps in and out linearly
    (clothoids) instead of stepping."""
    arc_m = math.radians(arc_deg) * radius_m
    total_m = lead_in_m + transition_m + arc_m + transition_m + lead_out_m
    # Each piece's curvature is the mean over it (16 samples), so a piece the arc's end
    # cuts through turns by exactly its share and the total turn is exact.
    fine = _segment_midpoints(total_m, spacing_m / 16.0)
    s = fine[: len(fine) // 16 * 16]
    kappa = (1.0 if left else -1.0) / radius_m
    edges = np.cumsum([0.0, lead_in_m, transition_m, arc_m, transition_m])
    shape = np.where(
        s < edges[1], 0.0,
        np.where(s < edges[2], (s - edges[1]) / max(transition_m, 1e-9),
        np.where(s < edges[3], 1.0,
        np.where(s < edges[4], (edges[4] - s) / max(transition_m, 1e-9), 0.0))),
    )  # fmt: skip
    return integrate_curvature(kappa * shape.reshape(-1, 16).mean(axis=1), spacing_m)


@dataclass(frozen=True)
class OffRoadParams:
    """The paper's off-road course, as a recipe: curvature changing all the time."""

    length_m: float = MILE_M
    min_radius_m: float = 15.0
    max_radius_m: float = 120.0
    straight_fraction: float = 0.25  # of the segments
    segment_min_m: float = 15.0
    segment_max_m: float = 60.0
    transition_m: float = 12.0  # clothoid between two curvatures
    # Keep the trail going somewhere: past this heading away from the start's, the next
    # curve turns back (a trail does not circle; the course does not cross itself often).
    heading_leash_rad: float = math.radians(75.0)
    spacing_m: float = 0.5


def off_road_course(seed: int, params: OffRoadParams = OffRoadParams()) -> FloatArray:
    """Seeded; the same seed gives the same course on every machine (numpy's PCG64)."""
    rng = np.random.default_rng(seed)
    knots_s = [0.0]
    knots_kappa = [0.0]
    s_m = 20.0  # starts straight: the vehicle is placed on it
    knots_s.append(s_m)
    knots_kappa.append(0.0)
    heading_rad = 0.0
    while s_m < params.length_m:
        if rng.random() < params.straight_fraction:
            kappa = 0.0
        else:
            radius = math.exp(
                rng.uniform(math.log(params.min_radius_m), math.log(params.max_radius_m))
            )
            sign = 1.0 if rng.random() < 0.5 else -1.0
            if abs(heading_rad) > params.heading_leash_rad:
                sign = -math.copysign(1.0, heading_rad)
            kappa = sign / radius
        length = rng.uniform(params.segment_min_m, params.segment_max_m)
        # heading gained: the ramp from the last curvature, then the segment
        heading_rad += 0.5 * (knots_kappa[-1] + kappa) * params.transition_m + kappa * length
        s_m += params.transition_m
        knots_s.append(s_m)
        knots_kappa.append(kappa)
        s_m += length
        knots_s.append(s_m)
        knots_kappa.append(kappa)
    s = _segment_midpoints(params.length_m, params.spacing_m)
    kappa_s = np.interp(s, knots_s, knots_kappa)
    return integrate_curvature(kappa_s, params.spacing_m)


def course_length_m(points_m: FloatArray) -> float:
    return float(np.sum(np.hypot(*np.diff(points_m, axis=0).T)))
