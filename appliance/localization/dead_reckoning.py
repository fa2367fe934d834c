"""Dead reckoning: the vehicle's pose in a local frame that never jumps (Stanley et al., Fig. 11).

The local frame is where the route tracker works: integrated from speed and the heading
(or a yaw rate), the pose in it moves only as the vehicle does, whatever the GNSS fixes
do; ``appliance.localization.frame_blend`` brings the route into it. The history lets a
fix be paired with where the vehicle was at the fix's measurement time, not when the
fix arrived.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

from appliance.localization.compound import wrap_angle_rad
from drivers.geometry import Pose2D

_ORIGIN = Pose2D(0.0, 0.0, 0.0)


@dataclass(frozen=True)
class DeadReckoningParams:
    history_s: float = 2.0  # how far back ``pose_at`` reaches: the fix latency and then some


class DeadReckoning:
    """The vehicle in the local frame, integrated from speed and heading or yaw rate.

    Each step moves along the arc of constant curvature joining the two samples (speed
    and yaw rate averaged over the step): exact for a constant turn, and continuous
    whatever the inputs, which is all the local frame must be.
    """

    def __init__(self, params: DeadReckoningParams | None = None) -> None:
        self.params = params or DeadReckoningParams()
        self.reset()

    def reset(self, pose: Pose2D = _ORIGIN) -> None:
        self._x_m, self._y_m, self._yaw_rad = pose.x_m, pose.y_m, pose.yaw_rad
        self._time_s: float | None = None
        self._speed_mps = 0.0
        self._slip_rad = 0.0
        self._yaw_rate_rps = 0.0
        self._times_s: list[float] = []
        self._poses: list[tuple[float, float, float]] = []  # yaw unwrapped, for interpolation

    @property
    def pose(self) -> Pose2D:
        return Pose2D(self._x_m, self._y_m, wrap_angle_rad(self._yaw_rad))

    def update(
        self,
        speed_mps: float,
        now_s: float,
        *,
        heading_rad: float | None = None,
        yaw_rate_rps: float | None = None,
        slip_rad: float = 0.0,
    ) -> Pose2D:
        """Advance to ``now_s``; give exactly one of ``heading_rad`` and ``yaw_rate_rps``.

        ``slip_rad`` is the direction of travel of the tracked point against the heading:
        a vehicle whose rear wheels steer too does not move where it points (Stanley et
        al.'s model: ``tan(beta) = (tan(phi_f) - tan(phi_r)) / 2`` at the centre), and on a
        15 m arc at 10 mph ignoring it walks the local pose off by metres per minute."""
        if (heading_rad is None) == (yaw_rate_rps is None):
            raise ValueError("give exactly one of heading_rad and yaw_rate_rps")
        turn = heading_rad if heading_rad is not None else yaw_rate_rps
        assert turn is not None
        if not all(math.isfinite(v) for v in (speed_mps, now_s, turn, slip_rad)):
            raise ValueError("dead reckoning needs finite speed, time and heading")
        if self._time_s is None:
            if heading_rad is not None:
                self._yaw_rad = heading_rad
        else:
            dt_s = now_s - self._time_s
            if dt_s < 0.0:
                raise ValueError(f"time went backwards by {-dt_s} s")
            if heading_rad is not None:
                delta_rad = wrap_angle_rad(heading_rad - self._yaw_rad)
            else:
                assert yaw_rate_rps is not None
                delta_rad = 0.5 * (self._yaw_rate_rps + yaw_rate_rps) * dt_s
            distance_m = 0.5 * (self._speed_mps + speed_mps) * dt_s
            half = 0.5 * delta_rad
            chord_m = distance_m * (math.sin(half) / half if abs(half) > 1e-9 else 1.0)
            travel_rad = self._yaw_rad + half + 0.5 * (self._slip_rad + slip_rad)
            self._x_m += chord_m * math.cos(travel_rad)
            self._y_m += chord_m * math.sin(travel_rad)
            self._yaw_rad += delta_rad
        self._time_s, self._speed_mps, self._slip_rad = now_s, speed_mps, slip_rad
        if yaw_rate_rps is not None:
            self._yaw_rate_rps = yaw_rate_rps
        self._remember(now_s)
        return self.pose

    def _remember(self, now_s: float) -> None:
        self._times_s.append(now_s)
        self._poses.append((self._x_m, self._y_m, self._yaw_rad))
        cut = bisect.bisect_left(self._times_s, now_s - self.params.history_s)
        if cut > 1:  # keep one sample at or before the cut, to interpolate from
            del self._times_s[: cut - 1], self._poses[: cut - 1]

    def pose_at(self, time_s: float) -> Pose2D | None:
        """The pose at a past time (a fix's measurement time); None outside the history."""
        if not self._times_s or not self._times_s[0] <= time_s <= self._times_s[-1]:
            return None
        i = bisect.bisect_left(self._times_s, time_s)
        if self._times_s[i] == time_s:
            x, y, yaw = self._poses[i]
            return Pose2D(x, y, wrap_angle_rad(yaw))
        t0, t1 = self._times_s[i - 1], self._times_s[i]
        f = (time_s - t0) / (t1 - t0)
        (x0, y0, a0), (x1, y1, a1) = self._poses[i - 1], self._poses[i]
        return Pose2D(x0 + f * (x1 - x0), y0 + f * (y1 - y0), wrap_angle_rad(a0 + f * (a1 - a0)))
