"""A scan's beams as points in the output frame, converted once for every later stage.

The input is the sensor frame the rest of the code base uses (x straight out of the
scanner's window, angles counter-clockwise; ``drivers.lms111.mounted`` subtracts the
device's 90° once), plus ``frame``: the scanner's pose in the frame the features are
wanted in. With the mount pose that is the vehicle frame, with the identity pose the
sensor frame itself.

Every beam keeps its index, echo or not, so that segments, features and the occlusion
and isolation tests (which look at the beam *next to* a cluster) can all speak in beam
indices. A beam without an echo (range 0, or anything not finite) is marked invalid and
its point is put at the sensor origin: a finite placeholder nobody reads, rather than a
NaN that would poison a sum.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt

from appliance.perception.jit import F64, IN_1D, IN_2D, IN_BOOL, kernel
from appliance.perception.types import BoolArray, FloatArray
from drivers.geometry import Pose2D

IDENTITY = Pose2D(0.0, 0.0, 0.0)


@dataclass(frozen=True, eq=False)
class ScanPoints:
    """One scan in the output frame; every array has one row per beam.

    ``ranges_m`` are the measured ranges minus the calibrated offset (0 where invalid);
    ``directions`` are the unit beam directions in the output frame, which the fits
    need because the range error of a point lies along its beam (with or without an
    echo; along the frame's yaw where the angle is not finite). Arrays may be shared
    between scans of one scanner: they are all read-only.
    """

    xy_m: FloatArray  # (N, 2)
    ranges_m: FloatArray  # (N,)
    directions: FloatArray  # (N, 2)
    valid: BoolArray  # (N,)
    origin_xy_m: tuple[float, float]

    def __post_init__(self) -> None:
        for array in (self.xy_m, self.ranges_m, self.directions, self.valid):
            array.flags.writeable = False

    @property
    def count(self) -> int:
        return int(self.ranges_m.shape[0])

    def valid_xy_m(self) -> FloatArray:
        """(M, 2) points of the beams with an echo, in beam order."""
        points: FloatArray = self.xy_m[self.valid]
        return points


def scan_points(
    ranges_m: npt.ArrayLike,
    angles_rad: npt.ArrayLike,
    frame: Pose2D = IDENTITY,
    *,
    range_offset_m: float = 0.0,
) -> ScanPoints:
    """Polar beams in the sensor frame to Cartesian points in the output frame.

    ``range_offset_m`` is a scanner calibration: it is subtracted from every range with
    an echo before conversion (a range that drops to 0 or below becomes no echo).
    Raises ValueError only for arrays of mismatched or non-1-D shape: a caller's bug,
    not a property of the scene.
    """
    ranges = np.asarray(ranges_m, dtype=np.float64)
    angles = np.asarray(angles_rad, dtype=np.float64)
    if ranges.ndim != 1 or angles.shape != ranges.shape:
        raise ValueError(
            f"ranges_m and angles_rad must be 1-D of one length, got {ranges.shape}"
            f" and {angles.shape}"
        )
    directions, finite_angles = _BEAMS.get(angles, float(frame.yaw_rad))
    xy, corrected, valid = _points(
        ranges, directions, finite_angles, range_offset_m, float(frame.x_m), float(frame.y_m)
    )
    return ScanPoints(xy, corrected, directions, valid, (float(frame.x_m), float(frame.y_m)))


@kernel(IN_1D, IN_2D, IN_BOOL, F64, F64, F64)
def _points(ranges: FloatArray, directions: FloatArray, finite_angles: BoolArray,
            range_offset_m: float, origin_x_m: float, origin_y_m: float
            ) -> tuple[FloatArray, FloatArray, BoolArray]:  # fmt: skip
    """(points, ranges less the offset, echo) per beam: an echo is a finite range above
    0 on a finite angle, still above 0 less the offset (a non-finite offset drops
    every echo); a beam without one has range 0 and its point at the origin."""
    count = ranges.shape[0]
    xy = np.empty((count, 2))
    corrected = np.zeros(count)
    valid = np.zeros(count, dtype=np.bool_)
    for i in range(count):
        r = ranges[i]
        if math.isfinite(r) and finite_angles[i] and r > 0.0:
            if range_offset_m != 0.0:  # r − 0 is r: without an offset no echo drops
                r -= range_offset_m
            if r > 0.0:
                corrected[i], valid[i] = r, True
        xy[i, 0] = corrected[i] * directions[i, 0] + origin_x_m
        xy[i, 1] = corrected[i] * directions[i, 1] + origin_y_m
    return xy, corrected, valid


_T = TypeVar("_T")


class AngleCache(Generic[_T]):
    """What is worked out from a scanner's beam angles and one number (the frame's yaw,
    a threshold), kept for the next scans: a scanner's angles are the same scan after
    scan. The few kept are found by comparing the angles' bytes, not by hashing them:
    hashing a scan's 8 kB of angles costs more than comparing them with every entry.
    The values are shared: make them read-only."""

    def __init__(self, make: Callable[[FloatArray, float], _T], size: int = 8) -> None:
        self._make = make
        self._size = size
        self._kept: list[tuple[bytes, float, _T]] = []

    def get(self, angles: FloatArray, number: float) -> _T:
        """``make(angles, number)``, or what it gave for equal arguments before."""
        key = np.asarray(angles, dtype=np.float64).tobytes()
        for kept_key, kept_number, value in self._kept:
            if kept_number == number and kept_key == key:
                return value
        value = self._make(np.frombuffer(key, dtype=np.float64), number)
        self._kept.insert(0, (key, number, value))
        del self._kept[self._size :]
        return value


def _beam_directions(beam_angles: FloatArray, yaw_rad: float) -> tuple[FloatArray, BoolArray]:
    """The unit directions of the beams at ``beam_angles`` turned by the frame's yaw, as
    rows, and which angles are finite; a beam whose angle is not finite looks along the
    yaw. These cosines and sines are a fair part of a whole scan's arithmetic."""
    finite = np.isfinite(beam_angles)
    with np.errstate(invalid="ignore"):
        world = np.where(finite, beam_angles, 0.0) + yaw_rad
    directions = np.column_stack((np.cos(world), np.sin(world)))
    for array in (directions, finite):
        array.flags.writeable = False
    return directions, finite


_BEAMS = AngleCache(_beam_directions)
