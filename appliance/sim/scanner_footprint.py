"""The echoes a beam's footprint makes: `render_scan`'s weak returns, edges and posts.

A beam's central ray stands for the whole beam except where its footprint straddles two
surfaces (near an edge) or curves away (on a post): only those beams, a tenth of a scan,
are cast again as a fan of sub-rays across the footprint (``footprint_beams``), and the
receiver's view of their returns is taken (``footprint_echo``). The fan is cast like the
central rays.

Every function here gives bit for bit what the straightforward array code gives (the
figures of a recorded run must not move when the code gets faster): sums keep their order
and each value is computed by the same operations, only fewer of them are taken.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from appliance.sim.raycast import RayHits, beam_directions
from appliance.sim.scanner_errors import (
    BeamFootprint,
    RemissionLimit,
    ScannerErrors,
    first_strong_echo,
)

# Neighbouring central rays on different shapes whose ranges differ by less than this
# meet at a corner (a board and its side board, two walls): the footprint there averages
# ranges a few millimetres apart, so such a junction is not cast again.
JUNCTION_STEP_M = 0.02
_SIDES = np.array([0, 1])  # the beams either side of an edge


def echoes(
    hits: RayHits,
    remission: NDArray[np.float64],
    errors: ScannerErrors,
    n_segments: int,
    cast: Callable[[NDArray[np.float64]], RayHits],
    table: NDArray[np.float64],
    angles_rad: NDArray[np.float64],
    step_rad: float,
    max_range_m: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """True ranges and remissions of the echoes the device detects (0 = none): the
    central rays', the weak ones dropped, and the footprint's mix near edges.

    ``remission`` is what each central ray hit (``table`` indexed by shape number, the
    last entry 0 for none; segments' numbers below ``n_segments``); ``cast`` casts the
    scan's shapes along (beams, 2) directions, called only if some beam is cast again
    (none is if the scanner is blind); ``angles_rad`` are the beams' in the world.
    """
    ranges, cast_remission = hits.ranges_m, remission
    limit, footprint = errors.remission_limit, errors.footprint
    if limit is not None:
        # The weak echoes, as echo_energy(...) < min_energy; where nothing was hit the
        # energy is nan here instead of 0, and the range and remission are 0 either way.
        with np.errstate(divide="ignore", invalid="ignore"):
            energy = ranges * ranges
            np.divide(remission, energy, out=energy)
        weak = energy < limit.min_energy
        ranges = np.where(weak, 0.0, ranges)  # fresh arrays: the cast's may be read-only
        remission = np.where(weak, 0.0, remission)
    if footprint is None:
        return ranges, remission
    beams = footprint_beams(hits, n_segments, footprint, step_rad, max_range_m)
    if beams.size == 0:
        return ranges, remission
    if limit is None:
        ranges, remission = np.array(ranges), np.array(remission)
    sub_m, sub_remission = _cast_footprints(
        hits.ranges_m.take(beams),
        cast_remission.take(beams),
        angles_rad.take(beams),
        cast,
        table,
        footprint,
        max_range_m,
    )
    ranges[beams], remission[beams] = footprint_echo(sub_m, sub_remission, footprint, limit)
    return ranges, remission


def footprint_beams(
    hits: RayHits, n_segments: int, footprint: BeamFootprint, step_rad: float, max_range_m: float
) -> NDArray[np.intp]:
    """The beams whose central ray does not stand for their footprint: cast them again.

    Those that may reach across an edge: where neighbouring central rays hit different
    shapes (or one misses) at ranges more than ``JUNCTION_STEP_M`` apart. A beam k beams
    away from the edge reaches it if the footprint's half-angle at the nearer of the
    edge's two ranges exceeds k beam steps; the farthest such reach over the scan is used
    for every edge. And those on a circle (shapes from ``n_segments`` on): across a
    post's curve the footprint's ranges differ by millimetres to centimetres.
    """
    ranges, index = hits.ranges_m, hits.hit_index
    count = ranges.shape[0]
    near = index >= n_segments
    left, right = ranges[:-1], ranges[1:]
    jump = index[1:] != index[:-1]
    step = right - left
    np.abs(step, out=step)
    jump &= step > JUNCTION_STEP_M
    edges = jump.nonzero()[0]
    if edges.size == 0:
        return near.nonzero()[0]
    # The half-angle falls with the range, so the largest is the one at the nearest
    # range beside an edge (a miss counts as the maximum range).
    sides = ranges.take(np.add.outer(edges, _SIDES))
    nearest = np.minimum.reduce(sides, None, where=sides > 0.0, initial=max_range_m)
    reach = min(int(footprint.half_angle_rad(nearest) // step_rad), count)
    reached = np.add.outer(edges, np.arange(-reach, reach + 2)).ravel()
    np.maximum(reached, 0, out=reached)
    np.minimum(reached, count - 1, out=reached)
    near[reached] = True
    return near.nonzero()[0]


def _cast_footprints(
    central_m: NDArray[np.float64],
    central_remission: NDArray[np.float64],
    angles_rad: NDArray[np.float64],
    cast: Callable[[NDArray[np.float64]], RayHits],
    table: NDArray[np.float64],
    footprint: BeamFootprint,
    max_range_m: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Ranges and remissions of every sub-ray, (beams, sub_rays) each: the central ray's
    (already cast) in the middle, the others cast here.

    The fan's half-angle is the footprint's at the central ray's range (at the maximum
    range for a beam whose central ray has no hit)."""
    side = footprint.side_offsets
    half = footprint.half_angle_rad(np.where(central_m > 0.0, central_m, max_range_m))
    fan = angles_rad[:, None] + np.multiply.outer(half, side)
    sub = cast(beam_directions(fan.ravel()))
    beams, middle = central_m.size, side.size // 2
    full = np.empty((2, beams, side.size + 1))  # ranges, remissions
    full[0, :, middle] = central_m
    full[1, :, middle] = central_remission
    sides = np.empty((2, beams, side.size))
    sides[0] = sub.ranges_m.reshape(beams, side.size)
    table.take(sub.hit_index, out=sides[1].reshape(-1))
    full[:, :, :middle] = sides[:, :, :middle]
    full[:, :, middle + 1 :] = sides[:, :, middle:]
    return full[0], full[1]


def footprint_echo(
    ranges_m: NDArray[np.float64],
    remission: NDArray[np.float64],
    footprint: BeamFootprint,
    limit: RemissionLimit | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The echo of each beam from its sub-rays' (beams, sub_rays) hits: range and remission.

    Each sub-ray carries its profile weight of the beam's energy; the returned remission
    is the one a target filling the beam at the echo's range would need for the echo's
    energy (a beam half on a board reports about half its remission). Without a
    remission limit every hit counts, even of a black (0) surface.
    """
    _, weights = footprint.profile
    if limit is None:
        remission = np.maximum(remission, 1e-9)
    # echo_energy(ranges_m, remission) (0 where nothing was hit), times the weights.
    energy = ranges_m * ranges_m  # 0 where nothing was hit, and left so
    np.divide(remission, energy, out=energy, where=ranges_m > 0.0)
    energy *= weights
    min_energy = 0.0 if limit is None else limit.min_energy
    echo_m, echo_energy_ = first_strong_echo(ranges_m, energy, footprint.pulse_merge_m, min_energy)
    return echo_m, echo_energy_ * echo_m * echo_m
