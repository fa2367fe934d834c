"""The simulated PC104's own steering loop: a PI controller per motion pattern on the pose.

Qian et al.'s PC104 "runs a PID per pattern on the current and the expected pose". When
the high level asks for it (HL_ExpectedPose.SteeringLoop = PC104) the twin does the same:
the HL still chooses the pattern and the speed, and the twin turns the pose error into
wheel angles itself, from HL_Pose and HL_ExpectedPose alone (a PC104 has no scanner):

- STRAIGHT: every row straight;
- REAR_STEER: the rear row's angle that turns the heading error away, through the
  rear-steer kinematics (yaw rate = -v tan(delta_r) / L), with a PI on the heading error;
- OBLIQUE: the crab angle that moves the control point (the front end's centre, where the
  teeth are) sideways onto the expected pose's axis, with a PI on that lateral error.

The gains are scheduled by speed (an angle per error would turn the wheels too far at
walking pace and too little at speed), the angles are limited and rate-limited as a
hydraulic steering allows. Pure: time comes in as ``dt_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.geometry import Pose2D
from drivers.pc104.messages import MotionPattern

# The patterns this loop steers; the others keep the HL's set-points.
POSE_PATTERNS = frozenset({MotionPattern.STRAIGHT, MotionPattern.OBLIQUE, MotionPattern.REAR_STEER})


@dataclass(frozen=True)
class PoseLoopParams:
    wheelbase_m: float = 6.0
    control_point_forward_m: float = 6.0  # the front end's centre ahead of the centre
    heading_kp_per_s: float = 0.4  # yaw rate per radian of heading error
    heading_ki_per_s2: float = 0.02
    lateral_kp_per_s: float = 0.4  # sideways speed per metre of lateral error
    lateral_ki_per_s2: float = 0.02
    integral_limit_rad: float = math.radians(1.0)  # heading error-seconds
    integral_limit_m: float = 0.02  # lateral error-seconds
    min_speed_mps: float = 0.01  # below this the wheels hold their angle
    max_rear_steer_rad: float = math.radians(20.0)
    max_crab_rad: float = math.radians(15.0)
    max_rate_rad_per_s: float = math.radians(3.0)


def pose_errors(pose: Pose2D, expected: Pose2D, control_forward_m: float) -> tuple[float, float]:
    """Heading error and the control point's lateral offset, in the expected pose's frame."""
    heading = math.remainder(pose.yaw_rad - expected.yaw_rad, math.tau)
    x, y = pose.apply(control_forward_m, 0.0)  # the control point, in the site frame
    c, s = math.cos(expected.yaw_rad), math.sin(expected.yaw_rad)
    # Across the expected pose's axis, on which its own control point lies.
    lateral = -s * (x - expected.x_m) + c * (y - expected.y_m)
    return heading, lateral


class PoseLoop:
    """Wheel angles per pattern from the pose error; ``reset()`` at every pattern change."""

    def __init__(self, params: PoseLoopParams = PoseLoopParams()) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._heading_integral = 0.0
        self._lateral_integral = 0.0
        self._pattern: MotionPattern | None = None
        self._last: tuple[float, float] | None = None

    def update(
        self,
        pattern: MotionPattern,
        speed_mps: float,
        pose: Pose2D,
        expected: Pose2D,
        current_front_rad: float,
        current_rear_rad: float,
        dt_s: float,
    ) -> tuple[float, float]:
        """(front, rear) physical wheel angles, left positive, for ``pattern``.

        ``speed_mps`` is the signed speed (the measured one: the loop steers the vehicle
        as it moves); the wheels' current angles are where the rate limit starts from."""
        p = self.params
        if pattern is not self._pattern:
            self.reset()
            self._pattern = pattern
        heading, lateral = pose_errors(pose, expected, p.control_point_forward_m)
        moving = abs(speed_mps) >= p.min_speed_mps
        speed = speed_mps if moving else math.copysign(p.min_speed_mps, speed_mps or 1.0)
        front, rear = 0.0, 0.0
        if pattern is MotionPattern.REAR_STEER:
            if moving:
                self._heading_integral = _clamp(
                    self._heading_integral + heading * dt_s, p.integral_limit_rad
                )
            yaw_rate = -(
                p.heading_kp_per_s * heading + p.heading_ki_per_s2 * self._heading_integral
            )
            rear = _clamp(-math.atan(yaw_rate * p.wheelbase_m / speed), p.max_rear_steer_rad)
        elif pattern is MotionPattern.OBLIQUE:
            if moving:
                self._lateral_integral = _clamp(
                    self._lateral_integral + lateral * dt_s, p.integral_limit_m
                )
            sideways = -(
                p.lateral_kp_per_s * lateral + p.lateral_ki_per_s2 * self._lateral_integral
            )
            ratio = _clamp(sideways / speed, 0.99)
            front = _clamp(math.asin(ratio) - heading, p.max_crab_rad)
        # Rate-limited from the angles last asked for (from the wheels' own angles when the
        # loop starts): the wheels lag what they are asked, and limiting from where they are
        # would creep instead of turning at the rate.
        last_front, last_rear = self._last or (current_front_rad, current_rear_rad)
        step = p.max_rate_rad_per_s * max(dt_s, 0.0)
        front = last_front + _clamp(front - last_front, step)
        rear = last_rear + _clamp(rear - last_rear, step)
        self._last = (front, rear)
        return front, rear


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


__all__ = ["POSE_PATTERNS", "PoseLoop", "PoseLoopParams", "pose_errors"]
