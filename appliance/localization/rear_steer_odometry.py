"""A rear-steered vehicle's odometry: its body velocity from speed and steering angle,
and the recent samples a scan's prediction is integrated through.

Kinouchi et al.'s forklift steers its rear axle and reports its speed (from its own
drive controller) and its steering angle. The samples are kept for a short while so that
a scan is predicted to its own time through every sample before it: a velocity between
two samples is their mean (the trapezoid rule), beyond the last one it is held for
``hold_s``, and after that the motion is unknown (a standing vehicle with a forklift's
top speed as its uncertainty) rather than guessed.

**Rear-steer kinematics.** Vehicle frame at the centre C, x forward, y left; the front
(drive) axle at ``+L/2``, unsteered; the rear axle at ``−L/2``, its wheels turned by the
reported angle δ (positive turns the vehicle left, so the rear wheels point to the
right, at ``−δ`` in the frame). With no slip each axle moves along its wheels. The body's
velocity at C is ``(vx, vy)`` and its yaw rate ω; a point at ``(a, 0)`` moves with
``(vx, vy + ω a)``. Front: ``vy + ω L/2 = 0``. Rear: ``(vy − ω L/2) / vx = tan(−δ)``.
Together: ``ω = vx tan δ / L`` and ``vy = −vx tan δ / 2``, so the velocity at C points
at ``β = −atan(tan δ / 2)`` (to the right while turning left: the tail swings out) and,
with ``v`` the speed at C, ``vx = v cos β``, ``vy = v sin β``, ``ω = v cos β tan δ / L``.
That is ``appliance.sim.vehicle.step``'s REAR_STEER (front angle 0, rear angle δ in its
counter-steer sense: ``β = atan((tan φf − tan φr)/2)``, ``ω = v cos β / L (tan φf +
tan φr)``), including its empirical sideslip gain ``1 / (1 + (v / V_char)²)`` on ω when
the caller gives a characteristic speed. ``v`` is the speed at the centre; a speed
measured on the (unsteered) drive axle is ``vx``, i.e. ``v cos β``: 24 % less at a 60°
lock, which such a vehicle's caller must divide out.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from appliance.localization.launcher_ekf import BodyMotion, LauncherEkf
from drivers.geometry import Pose2D

Velocity = tuple[float, float, float]
Matrix = list[list[float]]


@dataclass(frozen=True)
class OdometryParams:
    """How far the reported speed and steering angle are trusted.

    ``speed_sigma_*``: the drive controller's speed, an absolute and a relative part (a
    worn tyre's few percent). ``steer_sigma_rad``: the steering sensor's offset and play.
    Both are errors that last (an offset, a scale), not white noise: ``correlation_time_s``
    lets the prediction's variance grow with it (`BodyMotion`). ``hold_s``: a sample
    stands for this long past its time; then the motion is unknown, and the prediction
    takes a standing vehicle with ``unknown_*`` sigmas (a forklift's top speed within a
    few seconds)."""

    speed_sigma_mps: float = 0.02
    speed_sigma_fraction: float = 0.03
    steer_sigma_rad: float = math.radians(0.6)
    correlation_time_s: float = 1.0
    hold_s: float = 0.2
    unknown_speed_sigma_mps: float = 1.0
    unknown_yaw_rate_sigma_radps: float = 0.5
    history: int = 256


def rear_steer_velocity(
    speed_mps: float,
    steer_rad: float,
    wheelbase_m: float,
    characteristic_speed_mps: float = math.inf,
) -> Velocity:
    """``(vx, vy, ω)`` of the centre midway between the axles, rear axle steered by
    ``steer_rad`` (positive turns left), ``speed_mps`` the speed at the centre (module
    docstring). ``cos β = 2 / √(4 + tan²δ)``, ``sin β = −tan δ / √(4 + tan²δ)``."""
    tan_d = math.tan(steer_rad)
    k = 1.0 / math.sqrt(4.0 + tan_d * tan_d)
    gain = 1.0 / (1.0 + (speed_mps / characteristic_speed_mps) ** 2)
    vx = 2.0 * k * speed_mps
    return vx, -tan_d * k * speed_mps, vx * tan_d / wheelbase_m * gain


def rear_steer_motion(
    speed_mps: float,
    steer_rad: float,
    wheelbase_m: float,
    params: OdometryParams,
    characteristic_speed_mps: float = math.inf,
) -> BodyMotion:
    """`rear_steer_velocity` with its covariance ``J diag(σv², σδ²) Jᵀ``.

    With ``t = tan δ``, ``k = 1/√(4 + t²)`` and ``dt/dδ = 1 + t²``: ``∂vx/∂δ = −2vtk³(1+t²)``,
    ``∂vy/∂δ = −4vk³(1+t²)``, ``∂ω/∂δ = 8vgk³(1+t²)/L``; ``∂/∂v`` is ``(2k, −tk,
    2tk(g + v g')/L)`` with the sideslip gain ``g`` and ``g' = −2v g²/V²``."""
    v, wheelbase = speed_mps, wheelbase_m
    t = math.tan(steer_rad)
    k = 1.0 / math.sqrt(4.0 + t * t)
    k3 = k * k * k
    g = 1.0 / (1.0 + (v / characteristic_speed_mps) ** 2)
    dg = -2.0 * v / characteristic_speed_mps**2 * g * g
    sec2 = 1.0 + t * t
    d_speed = (2.0 * k, -t * k, 2.0 * t * k * (g + v * dg) / wheelbase)
    d_steer = (-2.0 * v * t * k3 * sec2, -4.0 * v * k3 * sec2, 8.0 * v * g * k3 * sec2 / wheelbase)
    var_v = (params.speed_sigma_mps + params.speed_sigma_fraction * abs(v)) ** 2
    var_d = params.steer_sigma_rad**2
    covariance = np.array(
        [[var_v * a * b + var_d * c * d for b, d in zip(d_speed, d_steer, strict=True)]
         for a, c in zip(d_speed, d_steer, strict=True)]
    )  # fmt: skip
    velocity = rear_steer_velocity(v, steer_rad, wheelbase, characteristic_speed_mps)
    return BodyMotion(np.array(velocity), covariance, params.correlation_time_s)


class _Sample(NamedTuple):
    t_s: float
    velocity: Velocity
    covariance: Matrix


class _Segment(NamedTuple):
    start_s: float
    end_s: float
    velocity: Velocity
    covariance: Matrix


class OdometryHistory:
    """The recent odometry samples, and the piecewise-constant motion between two times."""

    def __init__(self, params: OdometryParams) -> None:
        self.params = params
        speed_var = params.unknown_speed_sigma_mps**2
        yaw_rate_var = params.unknown_yaw_rate_sigma_radps**2
        self._unknown: Matrix = [
            [speed_var, 0.0, 0.0],
            [0.0, speed_var, 0.0],
            [0.0, 0.0, yaw_rate_var],
        ]
        self.samples: deque[_Sample] = deque(maxlen=params.history)
        self.out_of_order = 0

    def reset(self) -> None:
        self.samples.clear()
        self.out_of_order = 0

    @property
    def last_s(self) -> float | None:
        return self.samples[-1].t_s if self.samples else None

    def add(self, t_s: float, motion: BodyMotion) -> None:
        if self.samples and t_s <= self.samples[-1].t_s:
            self.out_of_order += 1
            return
        velocity = tuple(float(v) for v in motion.velocity)
        self.samples.append(_Sample(t_s, (velocity[0], velocity[1], velocity[2]),
                                    motion.covariance.tolist()))  # fmt: skip

    def forget_before(self, t_s: float) -> None:
        """Drop what no prediction from ``t_s`` on needs: all but the last sample before it."""
        while len(self.samples) >= 2 and self.samples[1].t_s <= t_s:
            self.samples.popleft()

    def segments(self, start_s: float, end_s: float) -> list[_Segment]:
        """The motion from ``start_s`` to ``end_s``, split at every sample's time."""
        samples = list(self.samples)
        inner = [s.t_s for s in samples]
        if samples:  # where the first and the last sample stop standing for the motion
            inner += [samples[0].t_s - self.params.hold_s, samples[-1].t_s + self.params.hold_s]
        cuts = [start_s, *sorted(t for t in inner if start_s < t < end_s), end_s]
        found = []
        for a, b in itertools.pairwise(cuts):
            if b > a:
                velocity, covariance = self._between(samples, a, b)
                found.append(_Segment(a, b, velocity, covariance))
        return found

    def _between(self, samples: list[_Sample], a: float, b: float) -> tuple[Velocity, Matrix]:
        """The mean velocity over ``[a, b]``, which no sample's time splits."""
        before = next((s for s in reversed(samples) if s.t_s <= a), None)
        after = next((s for s in samples if s.t_s >= b), None)
        hold = self.params.hold_s
        if before is not None and after is not None:
            span = after.t_s - before.t_s
            w = (0.5 * (a + b) - before.t_s) / span if span > 0.0 else 0.0
            velocity = tuple(
                (1.0 - w) * p + w * q for p, q in zip(before.velocity, after.velocity, strict=True)
            )
            covariance = [
                [(1.0 - w) * p + w * q for p, q in zip(rp, rq, strict=True)]
                for rp, rq in zip(before.covariance, after.covariance, strict=True)
            ]
            return (velocity[0], velocity[1], velocity[2]), covariance
        middle = 0.5 * (a + b)
        if before is not None and middle - before.t_s <= hold:
            return before.velocity, before.covariance
        if after is not None and after.t_s - middle <= hold:
            return after.velocity, after.covariance
        return (0.0, 0.0, 0.0), self._unknown

    def relative(self, start_s: float, end_s: float) -> Pose2D:
        """Where the vehicle is at ``end_s`` in its own frame at ``start_s``."""
        pose = Pose2D(0.0, 0.0, 0.0)
        for segment in self.segments(start_s, end_s):
            dt = segment.end_s - segment.start_s
            vx, vy, w = chord_velocity(segment.velocity, dt)
            pose = pose.compose(Pose2D(vx * dt, vy * dt, w * dt))
        return pose


def chord_velocity(velocity: Velocity, dt_s: float) -> Velocity:
    """The velocity whose straight step over ``dt_s`` ends where the arc of ``velocity``
    does: turned by half the heading change and shortened by sin(h)/h. The EKF's step is
    straight along the heading at its start; along an arc that lags by half a step's
    turn, ``ω dt / 2`` of the distance driven: 5 mm per metre at 0.5 rad/s in 20 ms
    steps, which the odometry test would see."""
    vx, vy, w = velocity
    half = 0.5 * w * dt_s
    if half == 0.0:
        return velocity
    scale = math.sin(half) / half
    c, s = math.cos(half) * scale, math.sin(half) * scale
    return c * vx - s * vy, s * vx + c * vy, w


def predict_through(ekf: LauncherEkf, odometry: OdometryHistory, t_s: float) -> bool:
    """``ekf.predict`` to ``t_s`` through each odometry segment. False: ``t_s`` is before
    the filter's time (a scan out of order), nothing changed."""
    start = ekf.t_s
    if start is None:
        raise RuntimeError("predict before reset: the filter has no pose")
    if t_s <= start:
        return ekf.predict(t_s, BodyMotion.still())
    for segment in odometry.segments(start, t_s):
        velocity = chord_velocity(segment.velocity, segment.end_s - segment.start_s)
        motion = BodyMotion(
            np.array(velocity), np.array(segment.covariance), odometry.params.correlation_time_s
        )
        if not ekf.predict(segment.end_s, motion):
            return False
    return True
