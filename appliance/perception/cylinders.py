"""When a cluster is the launcher's cylindrical landmark, and where its centre is.

A circle fits almost anything short and curved: a post, a person's back, the inside of
a wall corner, an arc cut short by something in front of it. The estimator gates on the
predicted position too (a 0.15 m post *is* indistinguishable from the landmark), but
what this module can refuse from the scan alone it refuses, each with its reason:

- too few points to fit two unknowns with any redundancy;
- not as wide as the cylinder (two-sided, so a 0.2 m post is refused too);
- not isolated: the beams just outside the cluster must see nothing, or something
  clearly farther than the cluster's ends. A nearer or equally near neighbour is a wall
  the "arc" is the corner of, a person standing beside it, or an occluder that has
  cut the arc short, and the centre fitted to that would be pulled off. The raw scan is
  read here, not the regions of interest, so a region does not make a cylinder look
  isolated;
- residual rms above the noise (with the known radius);
- the centre not behind the arc (a concave shape fits from the wrong side);
- a free radius that disagrees with the known one, when there are points to tell.

**The beam footprint.** At 10 m the LMS111's beam is 16 cm across, half the cylinder.
A beam whose footprint only touches the cylinder still reports it, at its own central
angle: the arc looks wider than the cylinder by about half a footprint, and its end
points lie outside the circle. So the width check allows for that, and the fit drops
the beams within a footprint half-angle of each end while enough points remain; in
simulation that removes a bias of the centre of 7-8 mm at 10 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.perception import circle_search as search
from appliance.perception.circle_search import coordinates, trimmed_arc
from appliance.perception.circles import REASONS, free_radius_mismatch_xy
from appliance.perception.gates import chi_square_quantile
from appliance.perception.jit import F64, I64, IN_1D, IN_2D, IN_BOOL, kernel
from appliance.perception.points import ScanPoints
from appliance.perception.types import (
    BoolArray,
    CircleFeature,
    FitRejection,
    FloatArray,
    RejectReason,
    ScannerModel,
)


@dataclass(frozen=True)
class CircleParams:
    """Landmark radius and acceptance thresholds, defaults for Qian et al.'s launcher.

    Four points: a 0.3 m pipe at 15 m with 0.25° beams. Width: the arc's width, less
    ``footprint_widening`` of a footprint, must be the diameter to within one beam
    spacing, ``footprint_widening_tolerance`` of a footprint (bright or dark surfaces
    widen more or less) and ``width_tolerance_m``; that tells a 0.2 m post from the
    0.3 m landmark out to 15 m, where neither the rms nor a free radius can.
    ``rms_gate_z``: the residuals, in units of the data sheet's σ, must pass a χ² test
    with ``n − 2`` degrees of freedom at this normal quantile (3.09: 99.9 %), i.e. an rms
    of at most 1.9σ for 4 points and 1.4σ for 30; σ along a beam bounds the residual's
    noise, so a true cylinder passes with room to spare.
    ``facing_fraction``: the centre must lie this many radii behind the arc's mean range
    (a full arc's is π/4 R). ``isolation_margin_m`` 0.2 m is many σ yet less than the
    0.5 m the launcher's cylinders stand in front of its boards.
    ``radius_check_points``: below that many points the free radius is too noisy to
    judge. ``edge_trim_sigmas``: an end point farther off the circle than that is a
    mixed echo, dropped and refitted.
    """

    radius_m: float = 0.15
    min_points: int = 4
    width_tolerance_m: float = 0.01
    footprint_widening: float = 0.5
    footprint_widening_tolerance: float = 0.25
    rms_gate_z: float = 3.09
    facing_fraction: float = 0.25
    isolation_margin_m: float = 0.2
    radius_check_points: int = 8
    radius_tolerance_m: float = 0.02
    trim_footprint_edges: bool = True
    edge_trim_sigmas: float = 4.0
    max_iterations: int = 50

    def __post_init__(self) -> None:
        if not self.radius_m > 0.0:
            raise ValueError(f"radius_m must be > 0, got {self.radius_m}")
        if self.min_points < 3:
            raise ValueError(f"min_points must be >= 3, got {self.min_points}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")


_FITS, _TOO_WIDE, _TOO_NARROW, _NOT_ISOLATED = 0, 1, 2, 3


@kernel(IN_2D, I64, I64)
def _angle_between(directions: FloatArray, i: int, j: int) -> float:
    """The unsigned angle between two beams' unit vectors."""
    ax, ay, bx, by = directions[i, 0], directions[i, 1], directions[j, 0], directions[j, 1]
    return abs(math.atan2(ax * by - ay * bx, ax * bx + ay * by))


@kernel(IN_2D, IN_1D, IN_BOOL, I64, I64, F64, F64, F64, F64, F64, F64, F64)
def _arc_checks(directions: FloatArray, ranges_m: FloatArray, valid: BoolArray, start: int,
                stop: int, radius_m: float, footprint_exit_m: float,
                footprint_divergence_rad: float, widening: float, widening_tolerance: float,
                width_tolerance_m: float, isolation_margin_m: float
                ) -> tuple[int, float, float, float]:  # fmt: skip
    """Whether the cluster [start, stop) could be the cylinder before any fit: (outcome,
    the beam step, the arc's span and the centre's range, both in the width's detail).

    **Width.** Whether the cluster subtends the angle the cylinder would, from where it
    is. Compared as angles, not lengths: a cylinder of radius R whose centre is d away
    shows the scanner an arc between its two tangents, ``2 asin(R / d)`` wide, and only
    the beams' directions are certain (a mixed echo at an end is off in range, never in
    angle). A chord at the arc's mean range would be short of the diameter by up to a
    third at 1 m, where the tangent points lie well behind the nearest point. The
    footprint widens the arc by about ``widening`` of its own angular size; a scanner
    without one (the ideal model) is inside the tolerance.

    **Isolation.** The beams just outside the cluster see nothing, or see it clearly
    farther; at the field of view's edge what is beside the arc is unknown.
    """
    beam_step = _angle_between(directions, start, start + 1)
    centre_m = radius_m + min(ranges_m[start:stop])
    span = _angle_between(directions, start, stop - 1)
    expected = 2.0 * math.asin(min(1.0, radius_m / centre_m))
    footprint_rad = (footprint_exit_m + footprint_divergence_rad * centre_m) / centre_m
    widened = expected + widening * footprint_rad
    allowed = beam_step + widening_tolerance * footprint_rad + width_tolerance_m / centre_m
    if span > widened + allowed:
        return _TOO_WIDE, beam_step, span, centre_m
    # The first and the last beam on the arc each lie up to a step inside its tangents.
    # A footprint wider than a step makes up for that (a beam whose footprint touches
    # the cylinder reports it); thin rays do not, and their arc can look two steps short.
    unseen = max(0.0, beam_step - 0.5 * footprint_rad)
    if span < widened - allowed - unseen:
        return _TOO_NARROW, beam_step, span, centre_m
    for beyond, edge in ((start - 1, start), (stop, stop - 1)):
        if not 0 <= beyond < ranges_m.shape[0]:
            return _NOT_ISOLATED, beam_step, span, centre_m
        if valid[beyond] and ranges_m[beyond] <= ranges_m[edge] + isolation_margin_m:
            return _NOT_ISOLATED, beam_step, span, centre_m
    return _FITS, beam_step, span, centre_m


def _across(centre_m: float, span_rad: float) -> str:
    return f"{2.0 * centre_m * math.sin(0.5 * span_rad):.3f} m across"


def fit_cylinder(
    points: ScanPoints,
    segment: tuple[int, int],
    params: CircleParams,
    scanner: ScannerModel,
) -> CircleFeature | FitRejection:
    """The cylinder landmark a segment shows, or the reason it is not one."""
    start, stop = segment
    if stop - start < max(params.min_points, 2):
        return FitRejection(RejectReason.TOO_FEW_POINTS, f"{stop - start} points")
    outcome, beam_step, span, centre_m = _arc_checks(
        points.directions, points.ranges_m, points.valid, start, stop, params.radius_m,
        scanner.footprint_exit_m, scanner.footprint_divergence_rad, params.footprint_widening,
        params.footprint_widening_tolerance, params.width_tolerance_m,
        params.isolation_margin_m,
    )  # fmt: skip
    if outcome == _TOO_WIDE:
        return FitRejection(RejectReason.TOO_WIDE, _across(centre_m, span))
    if outcome == _TOO_NARROW:
        return FitRejection(RejectReason.TOO_NARROW, _across(centre_m, span))
    if outcome == _NOT_ISOLATED:
        return FitRejection(RejectReason.NOT_ISOLATED)
    first, last = start, stop
    if params.trim_footprint_edges:
        range_m = float(np.add.reduce(points.ranges_m[start:stop])) / (stop - start)
        reach = scanner.footprint_half_angle_rad(range_m) / max(beam_step, 1e-9)
        trim = min(math.ceil(reach), (stop - start - params.min_points) // 2)
        first, last = start + trim, stop - trim
    xs, ys = coordinates(points.xy_m[first:last])
    ox, oy = points.origin_xy_m
    outcome, kept_first, kept_stop, centre, covariance, sums, rms, mean_range_m = trimmed_arc(
        xs, ys, ox, oy, params.radius_m, params.max_iterations, params.min_points,
        params.edge_trim_sigmas * scanner.sigma_m, scanner.sigma_m, scanner.floor_sigma_m,
    )  # fmt: skip
    if outcome != search.OK:
        detail = "the centre is not determined" if outcome == search.DEGENERATE else ""
        return FitRejection(REASONS[outcome], detail)
    n_points = kept_stop - kept_first
    allowed_rms = scanner.sigma_m * math.sqrt(
        chi_square_quantile(n_points - 2, params.rms_gate_z) / n_points
    )
    if rms > allowed_rms:
        return FitRejection(RejectReason.RMS_TOO_LARGE, f"rms {rms * 1e3:.1f} mm")
    cx, cy = float(centre[0]), float(centre[1])
    if math.hypot(cx - ox, cy - oy) - mean_range_m < params.facing_fraction * params.radius_m:
        return FitRejection(RejectReason.NOT_FACING)
    if n_points >= params.radius_check_points:
        free_radius = free_radius_mismatch_xy(
            xs[kept_first:kept_stop],
            ys[kept_first:kept_stop],
            (cx, cy, params.radius_m),
            sums,
            points.origin_xy_m,
            scanner,
            params.radius_tolerance_m,
            3.0,
            params.max_iterations,
        )
        if free_radius is not None:
            return FitRejection(RejectReason.RADIUS_MISMATCH, f"radius {free_radius:.3f} m")
    return CircleFeature(
        cx_m=cx,
        cy_m=cy,
        radius_m=params.radius_m,
        covariance=covariance,
        n_points=n_points,
        rms_m=rms,
        first_index=first + kept_first,
        last_index=first + kept_stop - 1,
    )
