"""The forklift's approach to a pallet (Kinouchi et al., 2.1): to where it can see the
pallet, look again, then the last straight from what it sees.

Phases:

- ``TO_VIEW``: follow the plan's path (``pallet_plan``) by pure pursuit anchored at
  the guide point (the unsteered front axle's middle, which moves along the heading:
  pure pursuit's arc geometry holds for it as for a car's rear axle), at the cruise
  speed, slower where the path turns (the wheels need time to turn at their rate, and
  the tail swings out), braking into the view pose; refused if the vehicle strays
  farther from the path than the plan's clearance allows for.
- ``REDETECT``: standing at the view pose, wait for detections of the target (a pallet
  of the same kind within ``redetect_gate_m`` of where the map puts it); refused after
  a timeout, so a wrong or missing pallet never becomes a guess.
- ``FINAL``: the last straight re-planned from the detections (``pallet_final``:
  its frame, the quintic reference and the exact curvature law), the target updated
  by every later detection near it (the pallet stays in view), at the final speed or
  slower where the reference bends faster than the wheels turn, slowing as
  ``v = min(v_final, sqrt(2 a d))`` with a creep to the stop with the fork tips
  ``final_gap_m`` before the face. If the detected pallet is too far off the line
  the vehicle stands on to line up within the standoff, it is refused with the
  detection kept (``detected_pallet``) for the caller to plan again from.
- ``DONE``: stopped there, aligned within the tolerances; otherwise ``REFUSED``: the
  forks are not pushed into a pallet they are not aligned with.

A lost pose (none, not finite, or too uncertain) stops the vehicle at once and is a
refusal when it lasts. The controller only *wishes*: a speed (never backwards) and an
effective steering angle (positive turns left), within the vehicle's limits; the mode
machine and the safety layer decide what of it is sent.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from appliance.guidance.pallet_approach_params import (
    PalletApproachParams,
    PalletOrder,
    PalletPhase,
    pose_sigma_m,
    speed_profile_mps,
)
from appliance.guidance.pallet_final import (
    DetectionFilter,
    FaceErrors,
    LateralReference,
    curvature_wish_per_m,
    face_errors,
    lateral_reference,
)
from appliance.guidance.pallet_geometry import EntryFace, nearest_entry_face
from appliance.guidance.pallet_plan import FloatArray, PalletPlan
from appliance.guidance.path_geometry import (
    Polyline,
    point_at_arc_length,
    project_onto_path,
    signed_cross_track_m,
)
from appliance.mapping.pallets import Pallet
from drivers.geometry import Pose2D

__all__ = ["PalletApproach", "PalletApproachParams", "PalletOrder", "PalletPhase"]

# The heading beyond which the final approach has lost the pallet's axis.
_TURNED_AWAY_RAD = math.radians(60.0)


class _Errors(NamedTuple):
    lateral_m: float = math.nan
    heading_rad: float = math.nan
    distance_m: float = math.nan


_NO_ERRORS = _Errors()


class PalletApproach:
    """``update(pose, covariance, speed, t, detection) -> PalletOrder``, one per cycle."""

    def __init__(self, plan: PalletPlan, params: PalletApproachParams | None = None) -> None:
        self.plan = plan
        self.params = params or PalletApproachParams()
        self._path = Polyline.from_points(plan.guide_xy_m)
        self._path.prepare()
        self._speeds = speed_profile_mps(plan, self.params)
        self._arc = plan.arc_m
        # The projection looks this many segments ahead of the last one (about 2 m).
        self._window = max(4, math.ceil(2.0 / max(float(np.diff(self._arc).mean()), 1e-3)))
        self._detections = DetectionFilter(
            self.params.detection_memory, self.params.detection_slope_prior_m
        )
        self.reset()

    def reset(self) -> None:
        self.phase = PalletPhase.TO_VIEW
        self.refused = ""
        # Refused at the view pose with the pallet seen too far off the line: a plan
        # from the detection may get there (one refused at the pallet cannot: the
        # planner drives forward only).
        self.plan_again = False
        self._segment = 0
        self._steer_rad = 0.0
        self._stopping = False
        self._lost_since_s: float | None = None
        self._redetect_since_s = 0.0
        self._last_t_s = 0.0
        self._rejected = ""
        self._detections.reset()
        self._travelled_m = 0.0  # by the estimate, from the view pose on
        self._last_pose: Pose2D | None = None
        self._reference: LateralReference | None = None

    def resume(self, t_s: float) -> None:
        """Going on after a pause (hold-to-move let go, the vehicle standing): the
        clocks that judge waiting start again, the plan and what was seen are kept.
        A pause is the worker's choice, not the pallet gone missing."""
        if self.phase is PalletPhase.REDETECT:
            self._redetect_since_s = t_s
        self._lost_since_s = None

    @property
    def detected_pallet(self) -> Pallet | None:
        """The target as detected so far (to plan again from, after a refusal)."""
        return self._detections.pallet_at(self._travelled_m)

    # -- the cycle ---------------------------------------------------------------

    def update(
        self,
        pose_estimate: Pose2D | None,
        pose_covariance: FloatArray | None,
        speed_mps: float,
        t_s: float,
        pallet_detection: Pallet | None = None,
    ) -> PalletOrder:
        """The wish for this cycle. ``pose_estimate`` is the vehicle centre's in the site
        frame, ``speed_mps`` the measured speed, ``pallet_detection`` a detection of
        the target (site frame) made this cycle, if any."""
        p = self.params
        now_s = t_s if math.isfinite(t_s) else self._last_t_s
        self._last_t_s = now_s
        moving = not (math.isfinite(speed_mps) and abs(speed_mps) <= p.standstill_mps)
        if self.phase in (PalletPhase.DONE, PalletPhase.REFUSED):
            return self._order(0.0)
        pose = self._usable(pose_estimate, pose_covariance)
        if pose is None:
            self._lost_since_s = now_s if self._lost_since_s is None else self._lost_since_s
            if now_s - self._lost_since_s > p.lost_pose_timeout_s:
                return self._refuse("the pose estimate is lost (none, not finite or too unsure)")
            return self._order(0.0, waiting="the pose estimate is lost")
        self._lost_since_s = None
        if self.phase is not PalletPhase.TO_VIEW and self._last_pose is not None:
            self._travelled_m += math.hypot(
                pose.x_m - self._last_pose.x_m, pose.y_m - self._last_pose.y_m
            )
        self._last_pose = pose
        if self.phase is PalletPhase.TO_VIEW:
            return self._to_view(pose, speed_mps, moving, now_s)
        if self.phase is PalletPhase.REDETECT:
            return self._redetect(pose, moving, now_s, pallet_detection)
        return self._final(pose, speed_mps, moving, pallet_detection)

    def _usable(self, pose: Pose2D | None, covariance: object) -> Pose2D | None:
        if pose is None or not all(math.isfinite(v) for v in pose):
            return None
        if pose_sigma_m(covariance) > self.params.max_position_sigma_m:
            return None
        return pose

    def _order(
        self, speed_mps: float, errors: _Errors = _NO_ERRORS, waiting: str = ""
    ) -> PalletOrder:
        """The wish, clamped to the limits whatever the arithmetic before it did."""
        p = self.params
        steer = self._steer_rad if math.isfinite(self._steer_rad) else 0.0
        steer = max(-p.max_steer_rad, min(p.max_steer_rad, steer))
        speed = max(0.0, min(p.cruise_speed_mps, speed_mps)) if math.isfinite(speed_mps) else 0.0
        if self.phase in (PalletPhase.DONE, PalletPhase.REFUSED):
            speed = 0.0
        return PalletOrder(
            self.phase,
            speed,
            steer,
            self.refused,
            waiting,
            errors.lateral_m,
            errors.heading_rad,
            errors.distance_m,
            self._detections.count,
            self._rejected,
        )

    def _refuse(self, reason: str, errors: _Errors = _NO_ERRORS) -> PalletOrder:
        self.phase = PalletPhase.REFUSED
        self.refused = reason
        return self._order(0.0, errors)

    def _steer_for_curvature(self, curvature_per_m: float) -> None:
        if math.isfinite(curvature_per_m):
            limit = self.params.max_steer_rad
            steer = math.atan(self.params.wheelbase_m * curvature_per_m)
            self._steer_rad = max(-limit, min(limit, steer))

    # -- TO_VIEW -------------------------------------------------------------------

    def _to_view(self, pose: Pose2D, speed_mps: float, moving: bool, now_s: float) -> PalletOrder:
        p = self.params
        gx, gy = pose.apply(self.plan.guide_forward_m, 0.0)
        projection = project_onto_path(
            self._path, gx, gy, self._segment, self._segment + self._window
        )
        self._segment = projection.segment_index
        arc = self._path.arc_at(projection)
        remaining = self._path.length_m - arc
        if remaining <= 1e-6:  # at or past the end: how far past, along the last heading
            end_x, end_y = self.plan.guide_xy_m[-1]
            end_yaw = float(self.plan.headings_rad[-1])
            remaining = -((gx - end_x) * math.cos(end_yaw) + (gy - end_y) * math.sin(end_yaw))
        i = projection.segment_index
        h0, h1 = float(self.plan.headings_rad[i]), float(self.plan.headings_rad[i + 1])
        path_heading = h0 + projection.fraction * math.remainder(h1 - h0, math.tau)
        errors = _Errors(
            signed_cross_track_m(self._path, projection, gx, gy),
            math.remainder(pose.yaw_rad - path_heading, math.tau),
            remaining,
        )
        if abs(errors.lateral_m) > p.max_path_deviation_m:
            return self._refuse(
                f"{abs(errors.lateral_m):.2f} m off the planned path: its clearance is spent",
                errors,
            )
        if self._stopping or remaining <= p.view_tolerance_m:
            self._stopping = True
            if moving:
                return self._order(0.0, errors)
            self._stopping = False
            self.phase = PalletPhase.REDETECT
            self._redetect_since_s = now_s
            return self._order(0.0, errors, "looking for the pallet")
        along_mps = abs(speed_mps) if math.isfinite(speed_mps) else p.cruise_speed_mps
        lookahead = min(p.lookahead_max_m, p.lookahead_min_m + p.lookahead_per_mps_s * along_mps)
        (goal_x, goal_y), _ = point_at_arc_length(self._path, projection, lookahead)
        dx, dy = goal_x - gx, goal_y - gy
        left = -math.sin(pose.yaw_rad) * dx + math.cos(pose.yaw_rad) * dy
        distance_sq = dx * dx + dy * dy
        if distance_sq > 1e-12:
            # Pure pursuit: the arc from the guide point, tangent to the heading,
            # through the goal has curvature 2 sin(α) / D = 2 left / D².
            self._steer_for_curvature(2.0 * left / distance_sq)
        limit = float(np.interp(arc, self._arc, self._speeds))
        braking = math.sqrt(2.0 * p.decel_mps2 * max(remaining, 0.0))
        return self._order(max(p.creep_speed_mps, min(limit, braking)), errors)

    # -- REDETECT ------------------------------------------------------------------

    def _redetect(
        self, pose: Pose2D, moving: bool, now_s: float, detection: Pallet | None
    ) -> PalletOrder:
        p = self.params
        if detection is not None:
            self._offer_first(detection)
        if self._detections.count >= p.redetect_samples and not moving:
            return self._start_final(pose)
        if now_s - self._redetect_since_s > p.redetect_timeout_s:
            why = f" (the last one rejected: {self._rejected})" if self._rejected else ""
            return self._refuse(
                f"the pallet was not detected again within {p.redetect_timeout_s:.0f} s{why}"
            )
        return self._order(0.0, waiting="looking for the pallet")

    def _offer_first(self, detection: Pallet) -> None:
        """A detection at the view pose: the target if it is of its kind, near where the
        map puts it, and near the earlier detections."""
        target = self.plan.target
        off_m = math.hypot(detection.x_m - target.x_m, detection.y_m - target.y_m)
        if detection.kind is not target.kind:
            self._rejected = f"a {detection.kind.value} pallet, not {target.kind.value}"
        elif not off_m <= self.params.redetect_gate_m:
            self._rejected = f"{off_m:.2f} m from where the map puts the target"
        elif self._detections.count and not self._tracked(detection):
            self._rejected = "away from the earlier detections"
        else:
            self._detections.add(detection, self._travelled_m)

    def _tracked(self, detection: Pallet) -> bool:
        off_m, off_rad = self._detections.distance_to(detection, self._travelled_m)
        return (
            detection.kind is self.plan.target.kind
            and off_m <= self.params.track_gate_m
            and off_rad <= self.params.track_gate_rad
        )

    def _face_errors(self, pose: Pose2D) -> FaceErrors | None:
        """The vehicle against the detected pallet's face that the plan chose."""
        pallet = self.detected_pallet
        if pallet is None:
            return None
        face: EntryFace = nearest_entry_face(pallet, self.plan.face.entry_yaw_rad)
        return face_errors(
            pose,
            face,
            self.plan.guide_forward_m,
            self.params.tips_forward_m,
            self.params.forks_offset_y_m,
        )

    def _start_final(self, pose: Pose2D) -> PalletOrder:
        """The reference from where the vehicle stands to the detected pallet's axis,
        reached ``settle_m`` before the stop; refused when it needs more curvature than
        allowed (the pallet is too far off to line up within the standoff)."""
        p = self.params
        errors = self._face_errors(pose)
        if errors is None:
            return self._refuse("no detection to approach")
        tips_ahead_m = p.tips_forward_m - self.plan.guide_forward_m
        settle_at = -(p.final_gap_m + p.settle_m) - tips_ahead_m
        room = settle_at - errors.guide_along_m
        self.plan_again = True  # what follows refuses only for a new plan's sake
        if room < p.min_correction_m:
            return self._refuse(
                f"too near the pallet to line up ({room:.2f} m of room): "
                "plan again from the detection"
            )
        reference = lateral_reference(
            errors.guide_along_m, errors.guide_lateral_m, errors.heading_rad, settle_at
        )
        allowed = p.reference_curvature_fraction * p.max_curvature_per_m
        if reference.max_curvature_per_m() > allowed or reference.max_slope() > 1.0:
            return self._refuse(
                f"the pallet is {errors.guide_lateral_m:+.2f} m, "
                f"{math.degrees(errors.heading_rad):+.1f}° off the line the vehicle stands "
                "on: plan again from the detection"
            )
        self._reference = reference
        self.plan_again = False
        self.phase = PalletPhase.FINAL
        return self._final(pose, 0.0, False, None)

    # -- FINAL ---------------------------------------------------------------------

    def _final(
        self, pose: Pose2D, speed_mps: float, moving: bool, detection: Pallet | None
    ) -> PalletOrder:
        p = self.params
        if detection is not None:
            if self._tracked(detection):
                self._detections.add(detection, self._travelled_m)
            else:
                self._rejected = "a detection away from the target's"
        face = self._face_errors(pose)
        if face is None or self._reference is None:
            return self._refuse("the final approach has no target")
        gap = -face.tips_along_m - p.final_gap_m
        errors = _Errors(face.tips_lateral_m, face.heading_rad, gap)
        if abs(face.heading_rad) > _TURNED_AWAY_RAD:
            return self._refuse("turned away from the pallet's axis", errors)
        if self._stopping or gap <= p.stop_tolerance_m:
            self._stopping = True
            return self._order(0.0, errors) if moving else self._at_stop(errors)
        # The curvature the reference has where the wheels will be when they get there.
        ahead_m = max(0.0, speed_mps if math.isfinite(speed_mps) else 0.0) * p.steer_lag_s
        y_r, slope_r, _ = self._reference.at(face.guide_along_m)
        curvature_r = self._reference.at(face.guide_along_m + ahead_m)[2]
        self._steer_for_curvature(
            curvature_wish_per_m(
                face.guide_lateral_m,
                face.heading_rad,
                (y_r, slope_r, curvature_r),
                p.convergence_length_m,
            )
        )
        speed = min(
            p.final_speed_mps,
            math.sqrt(2.0 * p.final_decel_mps2 * gap),
            self._steer_rate_speed_mps(self._reference, face.guide_along_m),
        )
        return self._order(max(p.creep_speed_mps, speed), errors)

    def _steer_rate_speed_mps(self, reference: LateralReference, along_m: float) -> float:
        """The speed at which the wheels turn as fast as the reference's curvature
        changes over the preview, at ``steer_rate_fraction`` of their rate:
        ``dδ/dt = v L (dκ/dx) / (1 + (L κ)²)``, taken at ``κ = 0`` (the worst case).
        Faster, the wheels fall behind the reference and the error they leave has to
        be taken out on the straight."""
        p = self.params
        rate = max(
            reference.curvature_rate_per_m2(along_m + p.steer_rate_preview_m * i / 4)
            for i in range(5)
        )
        if rate <= 0.0:
            return math.inf
        return p.steer_rate_fraction * p.max_steer_rate_rad_per_s / (p.wheelbase_m * rate)

    def _at_stop(self, errors: _Errors) -> PalletOrder:
        """Stopped at the pallet: done when aligned, refused otherwise."""
        p = self.params
        if (
            abs(errors.lateral_m) <= p.max_lateral_error_m
            and abs(errors.heading_rad) <= p.max_heading_error_rad
        ):
            self.phase = PalletPhase.DONE
            return self._order(0.0, errors)
        return self._refuse(
            f"stopped misaligned: the fork tips {1000 * errors.lateral_m:+.1f} mm off the "
            f"pallet's axis, the heading {math.degrees(errors.heading_rad):+.2f}°; "
            "the forks are not pushed in",
            errors,
        )
