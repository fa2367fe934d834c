"""A scan as the rest of the vehicle sees it: which scanner, where it sits, when it arrived.

The LMS111 numbers its beams in its own frame, 90° straight out of the window
(docs/protocols/lms111.md). Consumers (feature extraction, the estimator, safety fields)
want the vehicle frame: x forward, y left, origin at the rear axle. The conversion is done
once, here, from the mount pose in the configuration, so no consumer repeats the
``- 90°`` and gets it wrong (the classic LMS1xx pitfall: clearpath LMS1xx and sick_scan_xd
both subtract it in their ROS nodes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import cached_property
from typing import Protocol

import numpy as np
import numpy.typing as npt

from drivers.geometry import Pose2D
from drivers.lms111.scan import Scan

FloatArray = npt.NDArray[np.float64]

DEVICE_FORWARD_RAD = math.pi / 2.0  # the device angle that points along the scanner's x


class SensorMount(Protocol):
    """Where a scanner sits, as a vehicle file states it (``geometry.scanner_*_mount``).

    A protocol rather than the file's model: the driver says what it reads, the vehicle
    file's section (or a test's own object) provides it.
    """

    @property
    def x_m(self) -> float: ...

    @property
    def y_m(self) -> float: ...

    @property
    def yaw_deg(self) -> float: ...


def mount_pose(mount: SensorMount) -> Pose2D:
    """The configured mount (degrees) as a planar pose in the vehicle frame (radians)."""
    return Pose2D(mount.x_m, mount.y_m, math.radians(mount.yaw_deg))


@dataclass(frozen=True, eq=False)
class MountedScan:
    """One scan from one named scanner, with the mount it was taken from.

    ``host_receive_time_s`` is the monotonic time the telegram was read from the socket;
    ``device_time_us`` is the scanner's own clock, unwrapped (monotonic within one power-up,
    see `DeviceTimeUnwrapper`), for consumers that want the scanner's regular spacing
    rather than the host's network jitter.
    """

    scan: Scan
    sensor: str
    mount: Pose2D
    host_receive_time_s: float
    device_time_us: int

    def __getstate__(self) -> dict[str, object]:
        """Only the fields, as for `Scan`: the cached views are computed again."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @cached_property
    def angles_vehicle_rad(self) -> FloatArray:
        """Each beam's direction in the vehicle frame (counter-clockwise from x forward)."""
        angles: FloatArray = self.scan.angles_rad + (self.mount.yaw_rad - DEVICE_FORWARD_RAD)
        angles.flags.writeable = False
        return angles

    @cached_property
    def valid(self) -> npt.NDArray[np.bool_]:
        """Beams with an echo (the device sends 0 for "nothing seen")."""
        mask: npt.NDArray[np.bool_] = self.scan.ranges_m > 0.0
        mask.flags.writeable = False
        return mask

    def points_vehicle_m(self) -> FloatArray:
        """N x 2 (x, y) in metres in the vehicle frame, valid beams only, in beam order."""
        ranges = self.scan.ranges_m[self.valid]
        angles = self.angles_vehicle_rad[self.valid]
        points = np.empty((len(ranges), 2), dtype=np.float64)
        points[:, 0] = self.mount.x_m + ranges * np.cos(angles)
        points[:, 1] = self.mount.y_m + ranges * np.sin(angles)
        return points
