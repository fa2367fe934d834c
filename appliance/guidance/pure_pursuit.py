"""The path tracker: Stanley et al.'s pure pursuit for proportional four-wheel counter-steer.

Each cycle: the look-ahead from the speed (Fig. 7b), the goal that far *along the path*
from the anchor's projected nearest point (Fig. 7a), the angle eta to it from the anchor
(the array, Fig. 8) and the front wheel angle whose arc takes the anchor through the goal
(eq. 2 or eq. 3; the formulas and their signs are in ``pure_pursuit_math``). The rear
wheels follow as ``k`` times the front angle, counter-steering.

Where the paper's own model shows a systematic error, this goes further:

* **Sideslip.** The plant turns at ``G_ss = 1 / (1 + (v / V_char)^2)`` of the kinematic
  yaw rate, so a kinematic pure-pursuit arc is too wide at speed and the vehicle settles
  outside a curve. With ``sideslip_compensation`` the arc is computed for the plant the
  model describes: the commanded curvature divided by ``G_ss`` and the centre of rotation
  placed where ``G_ss`` moves it (``pure_pursuit_math`` module docstring).
* **Lag.** The wheels reach a command one servo lag later (and a fix not extrapolated to
  the cycle's time is a receiver latency old), so the anchor is first moved
  ``prediction_s`` ahead along its present arc (measured yaw rate if given, else the one
  the last command produces) and the goal is taken from there: the command is right when
  it acts, not when it was computed. With the default look-ahead it costs a little
  convergence speed; it is what keeps a short look-ahead or a late fix from oscillating.
* **The open form.** Eq. 3 assumes ``tan(k phi) / tan(phi) = k``; eq. 2 without that
  assumption costs a few fixed-point iterations (``solve_open_form``).

The output is a wish: clamped to the steering angle and rate limits so it is a realistic
one; the safety layer enforces its own limits whatever this asks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from appliance.guidance.path_geometry import (
    PathProjection,
    Polyline,
    goal_shift_m,
    path_curvature_per_m,
    point_at_arc_length,
    project_onto_path,
    signed_cross_track_m,
)
from appliance.guidance.pure_pursuit_math import (
    minimum_lookahead_m,
    minimum_turn_radius_m,
    predict_pose,
    solve_eq2,
    steer_eq3_rad,
)
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LookaheadSchedule:
    """``L(v) = clamp(offset + gain * v, min, max)``, after Leonard et al. (Fig. 7b).

    Defaults for the Husky at 2-4.5 m/s (2.5 m at 5 mph, 2.7 m at 10 mph), chosen with
    `dbw sim track` on ``appliance.sim.vehicle`` (G_ss, 0.15 s servo lag, 25 deg/s) with
    the curvature feed-forward on: the seeded off-road miles (arcs down to 15 m, fixes of
    sigma 5 cm) and the paper's tuning tests (3 m offsets on a straight and onto a 20 m
    arc, 5 and 10 mph). At 10 mph, RMS at the anchor on the mile / overshoot after a 3 m
    offset: 1 + 1 s * v (5.5 m): 8.9 cm / 17 cm; 0.5 + 0.5 s * v: 3.0 cm / 17 cm;
    0.5 + 0.3 s * v (1.8 m): 1.9 cm / 56 cm. The anchor 3 m ahead already lends the lead
    a longer look-ahead would give; shorter still overshoots a large offset, the paper's
    reason for a look-ahead growing with speed. The minimum of 2.5 m keeps localization
    noise from being amplified more than 5 mph needs. The calibration issue tunes them on
    the vehicle, as the paper did with its linear and arc tests.
    """

    offset_m: float = 0.5
    gain_s: float = 0.5
    min_m: float = 2.5
    max_m: float = 12.0

    def lookahead_m(self, speed_mps: float) -> float:
        return max(self.min_m, min(self.max_m, self.offset_m + self.gain_s * abs(speed_mps)))


class _GeometryFields(Protocol):
    @property
    def wheelbase_m(self) -> float: ...
    @property
    def counter_steer_ratio_k(self) -> float: ...
    @property
    def anchor_point_forward_m(self) -> float: ...
    @property
    def characteristic_speed_mps(self) -> float: ...


class _LimitFields(Protocol):
    @property
    def max_steer_angle_deg(self) -> float: ...
    @property
    def max_steer_rate_deg_per_s(self) -> float: ...


class VehicleFields(Protocol):
    """What :meth:`PursuitParams.from_config` reads of the vehicle file (``VehicleConfig``).

    A protocol, because guidance sits below ``appliance.config`` in the floor plan.
    """

    @property
    def geometry(self) -> _GeometryFields: ...
    @property
    def limits(self) -> _LimitFields: ...


@dataclass(frozen=True)
class PursuitParams:
    wheelbase_m: float
    counter_steer_ratio_k: float
    anchor_forward_m: float  # from the vehicle centre (midway between the axles)
    characteristic_speed_mps: float
    max_steer_angle_rad: float
    max_steer_rate_rad_per_s: float
    schedule: LookaheadSchedule = field(default_factory=LookaheadSchedule)
    # Goals up to this far off the heading never saturate the steering (look-ahead floor).
    linear_eta_rad: float = math.radians(30.0)
    solve_open_form: bool = True
    sideslip_compensation: bool = True
    # The steering servo's lag (the simulated servo's 0.15 s time constant). Add the fix
    # latency only if the pose is not already extrapolated to the cycle's time (the GNSS
    # input does extrapolate it).
    prediction_s: float = 0.15
    curvature_half_window_m: float = 2.0
    # Pure pursuit flies the arc through the goal, whose curvature is the path's averaged
    # over the look-ahead (weighted 2(L - u)/L^2): where the path's curvature changes it
    # turns early and cuts in, by 0.3 m at the ends of a 15 m arc at 10 mph. The goal is
    # moved sideways by what makes that arc's curvature the path's at the anchor; this
    # reads the path only, so the feedback loop (and its stability) is unchanged.
    curvature_feedforward: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.counter_steer_ratio_k <= 1.0:
            raise ValueError(
                f"counter_steer_ratio_k must lie in [0, 1]: {self.counter_steer_ratio_k}"
            )
        if not 0.0 < self.max_steer_angle_rad < math.pi / 2:
            raise ValueError(
                f"max_steer_angle_rad must lie in (0, pi/2): {self.max_steer_angle_rad}"
            )
        for name in ("wheelbase_m", "characteristic_speed_mps", "max_steer_rate_rad_per_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive: {getattr(self, name)}")
        if self.prediction_s < 0.0 or self.curvature_half_window_m <= 0.0:
            raise ValueError("prediction_s must be >= 0 and curvature_half_window_m > 0")
        # An anchor behind the centre of rotation swings the wrong way when the vehicle
        # turns (the law would steer it away from the path): not a pure pursuit anchor.
        virtual_axle_m = (
            self.wheelbase_m * self.counter_steer_ratio_k / (1.0 + self.counter_steer_ratio_k)
        )
        if self.anchor_from_rear_axle_m < virtual_axle_m - 1e-9:
            raise ValueError(
                f"the anchor ({self.anchor_from_rear_axle_m:.3f} m ahead of the rear axle) "
                f"must not lie behind the virtual rear axle ({virtual_axle_m:.3f} m)"
            )

    @classmethod
    def from_config(cls, config: VehicleFields) -> PursuitParams:
        """The geometry and limits from the vehicle file; tuning stays at its defaults
        (``dataclasses.replace`` for others)."""
        geometry, limits = config.geometry, config.limits
        return cls(
            wheelbase_m=geometry.wheelbase_m,
            counter_steer_ratio_k=geometry.counter_steer_ratio_k,
            anchor_forward_m=geometry.anchor_point_forward_m,
            characteristic_speed_mps=geometry.characteristic_speed_mps,
            max_steer_angle_rad=math.radians(limits.max_steer_angle_deg),
            max_steer_rate_rad_per_s=math.radians(limits.max_steer_rate_deg_per_s),
        )

    @classmethod
    def plain_two_wheel(cls, base: PursuitParams) -> PursuitParams:
        """Plain pure pursuit (eq. 1 with ``l_fw = 0``), the benchmark's comparison.

        The anchor is the rear axle and ``k = 0``: the law of a front-steered car, blind
        to the counter-steer and the array, without the sideslip and lag terms. The
        output's rear angle is then 0; on the Husky the linkage counter-steers the rear
        wheels anyway (the sim's COUNTER_STEER pattern applies its own ``k``), which is the
        paper's point: this law then leaves larger errors. Feed it the rear axle's pose
        (:meth:`anchor_pose` does that from the centre's). The same look-ahead schedule
        applies, but its floor becomes the full-lock radius (5.8 m for the Husky): a rear
        axle anchor has no lever to reach a goal 30° off any closer.
        """
        return replace(
            base,
            counter_steer_ratio_k=0.0,
            anchor_forward_m=-base.wheelbase_m / 2.0,
            solve_open_form=False,
            sideslip_compensation=False,
            prediction_s=0.0,
            curvature_feedforward=False,
        )

    @cached_property
    def anchor_from_rear_axle_m(self) -> float:
        """The paper's ``l_fw``: measured from the rear axle, not the centre."""
        return self.wheelbase_m / 2.0 + self.anchor_forward_m

    @cached_property
    def turn_floor_m(self) -> float:
        """The shortest look-ahead full lock still reaches, whatever the schedule."""
        k = self.counter_steer_ratio_k
        virtual_axle_from_rear_m = self.wheelbase_m * k / (1.0 + k)
        return minimum_lookahead_m(
            minimum_turn_radius_m(self.wheelbase_m, k, self.max_steer_angle_rad),
            self.anchor_from_rear_axle_m - virtual_axle_from_rear_m,
            self.linear_eta_rad,
        )

    @cached_property
    def lookahead_floor_m(self) -> float:
        """The schedule's minimum, raised to where full lock still reaches the goal (once:
        the parameters are frozen, and it is read every cycle)."""
        return max(self.schedule.min_m, self.turn_floor_m)

    def lookahead_m(self, speed_mps: float) -> float:
        return max(self.lookahead_floor_m, self.schedule.lookahead_m(speed_mps))

    def anchor_pose(self, centre_pose: Pose2D) -> Pose2D:
        """The anchor's pose from the vehicle centre's (same heading)."""
        return centre_pose.compose(Pose2D(self.anchor_forward_m, 0.0, 0.0))

    def sideslip_gain(self, speed_mps: float) -> float:
        return 1.0 / (1.0 + (speed_mps / self.characteristic_speed_mps) ** 2)


@dataclass(frozen=True)
class TrackerOutput:
    front_steer_rad: float  # clamped and rate-limited; positive turns left
    rear_steer_rad: float  # k * front, positive in the counter-steer direction
    lookahead_m: float
    goal_x_m: float
    goal_y_m: float
    goal_beyond_end: bool  # the goal lies on the continuation past the path's end
    eta_rad: float  # from the predicted anchor's heading to the goal, left positive
    cross_track_m: float  # at the anchor now, positive when left of the path
    path_curvature_per_m: float  # near the projection, left turns positive
    unclamped_front_steer_rad: float  # the law's answer before the angle and rate limits
    predicted_anchor: Pose2D


class PurePursuitTracker:
    """Pure pursuit with the anchor point, counter-steer, sideslip and lag terms.

    Forward travel only: a route driven the other way is handed over reversed by the
    planner (Fig. 5), and a negative speed counts as standstill here.
    """

    def __init__(self, params: PursuitParams) -> None:
        self.params = params
        self._front_steer_rad = 0.0

    def reset(self, front_steer_rad: float = 0.0) -> None:
        """Start over from the wheels' present angle, the rate limit's starting point."""
        self._front_steer_rad = max(
            -self.params.max_steer_angle_rad,
            min(self.params.max_steer_angle_rad, front_steer_rad),
        )

    def update(
        self,
        anchor_pose: Pose2D,
        speed_mps: float,
        path_m: FloatArray | Polyline,
        projection: PathProjection,
        dt_s: float,
        *,
        yaw_rate_radps: float | None = None,
    ) -> TrackerOutput:
        """One cycle. ``path_m`` is (N, 2) in travel order, in the pose's frame, or that
        path as a :class:`Polyline` built once when the path changes (saves the O(N)
        checks each cycle); ``projection`` is the anchor's nearest point on it (the
        planner's, or :func:`project_onto_path`). ValueError on non-finite or malformed
        input."""
        x_m, y_m, yaw_rad = anchor_pose
        finite = math.isfinite
        if not (finite(x_m) and finite(y_m) and finite(yaw_rad) and finite(speed_mps)):
            raise ValueError("anchor pose, speed and dt must be finite")
        if not finite(dt_s):
            raise ValueError("anchor pose, speed and dt must be finite")
        if yaw_rate_radps is not None and not math.isfinite(yaw_rate_radps):
            raise ValueError("yaw rate must be finite")
        if dt_s < 0.0:
            raise ValueError(f"dt_s must not be negative: {dt_s}")
        path = path_m if isinstance(path_m, Polyline) else Polyline.from_points(path_m)
        path.check(projection)
        p = self.params
        speed = max(0.0, speed_mps)
        lookahead = p.lookahead_m(speed)
        plant_gain = p.sideslip_gain(speed)

        predicted, predicted_projection = self._predict(
            anchor_pose, speed, plant_gain, path, projection, yaw_rate_radps
        )
        (goal_x, goal_y), beyond_end = point_at_arc_length(path, predicted_projection, lookahead)
        if p.curvature_feedforward:
            from_arc_m = path.arc_at(predicted_projection)
            shift = goal_shift_m(path, from_arc_m, lookahead, p.curvature_half_window_m)
            nx, ny = path.direction(path.segment_at_arc(from_arc_m + lookahead))
            goal_x, goal_y = goal_x - ny * shift, goal_y + nx * shift
        dx, dy = goal_x - predicted.x_m, goal_y - predicted.y_m
        distance = math.hypot(dx, dy)
        eta = (
            0.0
            if distance == 0.0
            else math.remainder(math.atan2(dy, dx) - predicted.yaw_rad, math.tau)
        )

        gain = plant_gain if p.sideslip_compensation else 1.0
        k = p.counter_steer_ratio_k
        if p.solve_open_form:
            wish = solve_eq2(
                eta, distance, p.wheelbase_m, p.anchor_from_rear_axle_m, k, sideslip_gain=gain
            ).phi_rad
        else:
            wish = steer_eq3_rad(
                eta, distance, p.wheelbase_m, p.anchor_from_rear_axle_m, k, sideslip_gain=gain
            )

        clamped = max(-p.max_steer_angle_rad, min(p.max_steer_angle_rad, wish))
        step = p.max_steer_rate_rad_per_s * dt_s
        front = max(self._front_steer_rad - step, min(self._front_steer_rad + step, clamped))
        self._front_steer_rad = front
        return TrackerOutput(
            front_steer_rad=front,
            rear_steer_rad=k * front,
            lookahead_m=lookahead,
            goal_x_m=goal_x,
            goal_y_m=goal_y,
            goal_beyond_end=beyond_end,
            eta_rad=eta,
            cross_track_m=signed_cross_track_m(path, projection, x_m, y_m),
            path_curvature_per_m=path_curvature_per_m(path, projection, p.curvature_half_window_m),
            unclamped_front_steer_rad=wish,
            predicted_anchor=predicted,
        )

    def _predict(
        self,
        anchor_pose: Pose2D,
        speed_mps: float,
        plant_gain: float,
        path: Polyline,
        projection: PathProjection,
        yaw_rate_radps: float | None,
    ) -> tuple[Pose2D, PathProjection]:
        """The anchor ``prediction_s`` ahead on its present arc, and its projection.

        The body's motion comes from the last command taken as the wheels' angle (the
        kinematic model: centre velocity at ``tan(beta) = (tan phi_f - tan phi_r) / 2``,
        yaw rate with ``G_ss``), its yaw rate replaced by the measured one when given. The
        anchor, ahead of the centre, also moves sideways by ``yaw_rate * anchor_forward``.
        """
        p = self.params
        if p.prediction_s == 0.0 or speed_mps == 0.0:
            return anchor_pose, projection
        tan_front = math.tan(self._front_steer_rad)
        tan_rear = math.tan(p.counter_steer_ratio_k * self._front_steer_rad)
        beta = math.atan((tan_front - tan_rear) / 2.0)
        forward = speed_mps * math.cos(beta)
        yaw_rate = (
            forward * (tan_front + tan_rear) * plant_gain / p.wheelbase_m
            if yaw_rate_radps is None
            else yaw_rate_radps
        )
        lateral = speed_mps * math.sin(beta) + yaw_rate * p.anchor_forward_m
        predicted = predict_pose(anchor_pose, forward, lateral, yaw_rate, p.prediction_s)
        # Search where the anchor can be by then: a wheelbase either side of its travel.
        here_m = path.arc_at(projection)
        first_segment = path.segment_at_arc(here_m - p.wheelbase_m)
        last_segment = path.segment_at_arc(here_m + speed_mps * p.prediction_s + p.wheelbase_m)
        return predicted, project_onto_path(
            path, predicted.x_m, predicted.y_m, first_segment, last_segment
        )
