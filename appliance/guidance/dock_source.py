"""The autopilot source ``dock``: the flat-bed into the launcher's troughs, as a wish.

Each cycle it gives every new scan to the launcher localizer, asks the docking controller
for a pattern, a speed and an angle, and returns them as a wish that the mode machine and
the safety layer may refuse. It refuses itself, with the reason the operator reads on the
panel and in `dbw status`, whenever docking cannot be trusted: the launcher not in view,
the localization lost or degraded, the vehicle outside the automatic zone (about 10 m in
front, small heading: Qian et al. 4.2) when the operator wants to engage, or the
controller giving up at the alignment gate. A refusal while engaged is a fault in the
core, so the vehicle stops.

The plan starts afresh at every engagement: while the operator drives, the controller is
reset each cycle and only the localizer keeps working, so the pose is ready to engage on.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from appliance.guidance.docking import (
    DockingCommand,
    DockingController,
    DockingParams,
    DockingPhase,
    docking_errors,
    lateral_sigma_m,
)
from appliance.localization.launcher_localizer import (
    LauncherLocalizer,
    LocalizationEstimate,
    LocalizationStatus,
    LocalizerParams,
    ScannerSetup,
)
from drivers.geometry import Pose2D
from drivers.lms111.mounted import DEVICE_FORWARD_RAD, MountedScan
from drivers.pc104.messages import MotionPattern


@dataclass(frozen=True)
class DockZone:
    """Where docking may be engaged (the automatic navigation zone)."""

    max_gap_m: float = 12.0
    max_lateral_m: float = 1.5
    max_heading_rad: float = math.radians(10.0)


@dataclass(frozen=True)
class DockSourceParams:
    docking: DockingParams = field(default_factory=DockingParams)
    localizer: LocalizerParams = field(default_factory=LocalizerParams)
    zone: DockZone = field(default_factory=DockZone)


@dataclass(frozen=True)
class Wish:
    """What the source hands the core; kept free of the core's types (which import us).

    ``pose`` is the geometric centre's estimate in the launcher frame whenever there is one
    (with its status: a PC104 that steers on it must know whether to trust it), and
    ``expected_pose`` the docked pose while a plan is being carried out: what the PC104
    link carries for a PC104 that closes the loop itself."""

    ready: bool
    reason: str
    pattern: MotionPattern | None
    speed_mps: float
    front_steer_rad: float
    rear_steer_rad: float
    status: Mapping[str, object]
    pose: Pose2D | None = None
    pose_status: LocalizationStatus = LocalizationStatus.LOST
    expected_pose: Pose2D | None = None


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None or not math.isfinite(value) else round(value, digits)


def estimate_status(estimate: LocalizationEstimate) -> dict[str, object]:
    """The estimate for `dbw status`: pose, σ, quality, and what the filter rejected."""
    document: dict[str, object] = {
        "status": str(estimate.status),
        "reason": estimate.reason,
        "quality": estimate.quality,
        "accepted": dict(estimate.accepted),
        "rejected": dict(estimate.rejected),
        "nis": {k: _round(v, 2) for k, v in estimate.nis.items()},
    }
    if estimate.centre_pose is not None and estimate.centre_covariance is not None:
        cov = estimate.centre_covariance
        document["pose"] = {
            "x_m": round(estimate.centre_pose.x_m, 4),
            "y_m": round(estimate.centre_pose.y_m, 4),
            "heading_deg": round(math.degrees(estimate.centre_pose.yaw_rad), 3),
            "sigma_x_m": round(math.sqrt(max(float(cov[0, 0]), 0.0)), 4),
            "sigma_y_m": round(math.sqrt(max(float(cov[1, 1]), 0.0)), 4),
            "sigma_heading_deg": round(math.degrees(math.sqrt(max(float(cov[2, 2]), 0.0))), 3),
        }
    return document


class DockSource:
    name = "dock"

    def __init__(
        self, scanners: Mapping[str, ScannerSetup], params: DockSourceParams | None = None
    ) -> None:
        self.params = params or DockSourceParams()
        self.localizer = LauncherLocalizer(scanners, self.params.localizer)
        self.controller = DockingController(self.params.docking)
        self._seen: dict[str, MountedScan] = {}
        self.forget()

    def reset(self) -> None:
        """A new plan (the core calls this at every engagement). The pose is not the
        plan's: the localizer keeps tracking across engagements, or every engagement
        would begin with the launcher "not in view" until both scanners found it again."""
        self.controller.reset()

    def forget(self) -> None:
        """Everything, the pose included: the source as it was built."""
        self.localizer.reset()
        self.controller.reset()
        self._seen = {}

    def _feed(self, scans: Mapping[str, MountedScan | None], now_s: float) -> None:
        for name, mounted in scans.items():
            if mounted is None or self._seen.get(name) is mounted:
                continue
            self._seen[name] = mounted
            if name not in self.localizer.scanners:
                continue
            angles = mounted.scan.angles_rad - DEVICE_FORWARD_RAD
            self.localizer.update(
                name, mounted.scan.ranges_m, angles, mounted.host_receive_time_s, now_s
            )

    def docked_pose(self) -> Pose2D:
        """Where the geometric centre is when docked: the front end at the stand-off, on
        the launcher's axis, square to it."""
        p = self.params.docking
        return Pose2D(-p.standoff_m - p.front_end_forward_m, 0.0, 0.0)

    def wish(self, scans: Mapping[str, MountedScan | None], engaged: bool, now_s: float) -> Wish:
        self._feed(scans, now_s)
        estimate = self.localizer.estimate(now_s)
        wish = self._wish(estimate, engaged, now_s)
        planned = engaged and wish.ready
        return replace(
            wish,
            pose=estimate.centre_pose,
            pose_status=estimate.status,
            expected_pose=self.docked_pose() if planned else None,
        )

    def _wish(self, estimate: LocalizationEstimate, engaged: bool, now_s: float) -> Wish:
        status: dict[str, object] = {"localization": estimate_status(estimate)}
        if not engaged:
            self.controller.reset()

        def refuse(reason: str) -> Wish:
            status["refused"] = reason
            return Wish(False, reason, None, 0.0, 0.0, 0.0, status)

        if estimate.status is LocalizationStatus.LOST or estimate.centre_pose is None:
            if not self.localizer.ekf.initialized:
                return refuse(f"launcher not in view ({self.localizer.init_reason})")
            return refuse(f"localization lost: {estimate.reason}")
        if estimate.status is LocalizationStatus.DEGRADED:
            return refuse(f"localization degraded: {estimate.reason}")
        centre, covariance = estimate.centre_pose, estimate.centre_covariance
        gap, lateral, heading, teeth = docking_errors(centre, self.params.docking)
        status["docking"] = {
            "gap_m": round(gap, 4),
            "lateral_m": round(lateral, 4),
            "heading_deg": round(math.degrees(heading), 3),
            "teeth_lateral_m": [round(t, 4) for t in teeth],
            "lateral_sigma_m": _round(
                lateral_sigma_m(centre, covariance, self.params.docking.front_end_forward_m), 4
            ),
        }
        zone = self.params.zone
        if not engaged:
            outside = []
            if gap > zone.max_gap_m:
                outside.append(f"{gap:.1f} m out (at most {zone.max_gap_m:.0f})")
            if abs(lateral) > zone.max_lateral_m:
                outside.append(f"{lateral:+.2f} m off the axis")
            if abs(heading) > zone.max_heading_rad:
                outside.append(f"heading {math.degrees(heading):+.1f} deg")
            if outside:
                return refuse("outside the automatic zone: " + ", ".join(outside))
            status["docking"]["phase"] = "ready"  # type: ignore[index]
            return Wish(True, "", MotionPattern.STOP, 0.0, 0.0, 0.0, status)
        order: DockingCommand = self.controller.update(centre, covariance, now_s)
        status["docking"].update(  # type: ignore[attr-defined]
            {
                "phase": str(order.phase),
                "pattern": str(order.pattern),
                "pattern_switches": self.controller.switches,
                "attempt": self.controller.attempts,
            }
        )
        if order.refused:
            return refuse(order.refused)
        if order.phase is DockingPhase.DOCKED:
            return Wish(True, "", MotionPattern.STOP, 0.0, 0.0, 0.0, status)
        return Wish(
            True,
            "",
            order.pattern,
            order.speed_mps,
            order.front_steer_rad,
            order.rear_steer_rad,
            status,
        )
