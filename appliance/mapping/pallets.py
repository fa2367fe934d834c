"""Pallet maps: the reference objects Kinouchi et al. merge a worker's map through.

A pallet map is a list of 2D pallet poses, each with its covariance, in one map's frame
(the vehicle's map or the worker's). Every source (the worker's 3D cloud, a list of
object poses, the vehicle's own 2D scans) ends as one of these, so the merge
(`mapping.merge`) never knows where a pallet came from.

Conventions:

- A pallet's pose is its centre on the floor and the direction of its *length* (the
  longer side; for a square pallet, the side the forks enter), in radians.
- A pallet looks the same turned by its symmetry (half a turn for a rectangle, a quarter
  for a square): a posture is only known modulo `PalletKind.symmetry_rad`, and every
  comparison of postures goes through `posture_difference_rad`.
- Covariance is over (x, y, yaw) in m², m·rad, rad², in the map's frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import numpy.typing as npt

from drivers.geometry import Pose2D

FloatArray = npt.NDArray[np.float64]


class PalletKind(StrEnum):
    """The standard pallets the kit knows by their footprint (length x width in mm)."""

    EUR = "1200x800"  # ISO 6780 / EN 13698-1, the European pallet
    JIS = "1100x1100"  # ISO 6780 / JIS Z 0601 T11, the paper's (Japanese) pallet

    @property
    def length_m(self) -> float:
        return int(self.value.split("x")[0]) / 1000.0

    @property
    def width_m(self) -> float:
        return int(self.value.split("x")[1]) / 1000.0

    @classmethod
    def of_size(cls, length_m: float, width_m: float) -> PalletKind | None:
        """The standard pallet of this footprint (to the millimetre), or None."""
        dimensions = f"{round(length_m * 1000)}x{round(width_m * 1000)}"
        return next((kind for kind in cls if kind.value == dimensions), None)

    @property
    def symmetry_rad(self) -> float:
        """The turn that maps the footprint onto itself."""
        return math.pi / 2.0 if self.length_m == self.width_m else math.pi


def posture_difference_rad(a_rad: float, b_rad: float, symmetry_rad: float) -> float:
    """``a - b`` reduced to ``[-symmetry/2, symmetry/2)``: how far apart two postures of
    a footprint that repeats every ``symmetry_rad`` are."""
    half = 0.5 * symmetry_rad
    return (a_rad - b_rad + half) % symmetry_rad - half


@dataclass(frozen=True, eq=False)
class Pallet:
    """One pallet in one map: where it is, how sure that is, what it is."""

    x_m: float
    y_m: float
    yaw_rad: float
    covariance: FloatArray  # 3x3 over (x, y, yaw)
    kind: PalletKind = PalletKind.JIS
    name: str = ""
    # How many points (cloud or scan) the detection rests on; 0 for a pose given as such.
    support: int = 0

    def __post_init__(self) -> None:
        covariance = np.array(self.covariance, dtype=np.float64)
        if covariance.shape != (3, 3):
            raise ValueError(f"a pallet's covariance is 3x3, not {covariance.shape}")
        if not (
            math.isfinite(self.x_m) and math.isfinite(self.y_m) and math.isfinite(self.yaw_rad)
        ):
            raise ValueError(f"pallet {self.name!r} has a pose that is not finite")
        if not np.isfinite(covariance).all():
            raise ValueError(f"pallet {self.name!r} has a covariance that is not finite")
        covariance.flags.writeable = False
        object.__setattr__(self, "covariance", covariance)

    @property
    def pose(self) -> Pose2D:
        return Pose2D(self.x_m, self.y_m, self.yaw_rad)

    def corners_xy_m(self) -> list[tuple[float, float]]:
        """The footprint's corners, counter-clockwise from front-left (along +length)."""
        hl, hw = self.kind.length_m / 2.0, self.kind.width_m / 2.0
        return [self.pose.apply(x, y) for x, y in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))]


@dataclass(frozen=True)
class PalletMap:
    """The pallets one map holds, in that map's frame (named for messages and plots)."""

    pallets: tuple[Pallet, ...]
    frame: str = ""
    # Free text on where it came from: a file name, "vehicle scans at t=...", a seed.
    source: str = field(default="", compare=False)

    def __len__(self) -> int:
        return len(self.pallets)


def transform_pallet(transform: Pose2D, pallet: Pallet) -> Pallet:
    """``pallet`` (given in frame B) in frame A, where ``transform`` is B's pose in A;
    its covariance rotated with it (the transform taken as exact)."""
    c, s = math.cos(transform.yaw_rad), math.sin(transform.yaw_rad)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = transform.compose(pallet.pose)
    return Pallet(
        moved.x_m,
        moved.y_m,
        moved.yaw_rad,
        rotation @ pallet.covariance @ rotation.T,
        pallet.kind,
        pallet.name,
        pallet.support,
    )


def inverse_pose(pose: Pose2D) -> Pose2D:
    """The pose of the parent frame in ``pose``'s frame."""
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    return Pose2D(-(c * pose.x_m + s * pose.y_m), s * pose.x_m - c * pose.y_m, -pose.yaw_rad)
