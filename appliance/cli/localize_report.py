"""What `dbw localize` prints and draws of the track the localizer made of the recordings:
a line (or JSON object) per scan, the summary, and ``--png``'s picture (Qian et al.'s
Fig. 9). The replay itself is `appliance.cli.localize`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from appliance.cli.recordings import SCANNERS

if TYPE_CHECKING:
    from appliance.config.models import VehicleConfig
    from appliance.localization.launcher_localizer import LocalizationEstimate
    from appliance.localization.launcher_map import LauncherMap
    from drivers.geometry import Pose2D
    from drivers.lms111.recording import RecordedScans

STATUSES = ("ok", "degraded", "lost")
ELLIPSES_DRAWN = 20  # 2σ ellipses and heading arrows along the drawn track


@dataclass(frozen=True)
class TrackPoint:
    """The estimate right after one scan."""

    t_s: float  # the scan's receive time
    scanner: str
    scan_counter: int
    estimate: LocalizationEstimate


def _pose_sigma_json(pose: Pose2D | None, covariance: Any) -> dict[str, float] | None:
    if pose is None or covariance is None:
        return None
    sx, sy, syaw = (math.sqrt(max(float(covariance[i][i]), 0.0)) for i in range(3))
    return {
        "x_m": round(pose.x_m, 5),
        "y_m": round(pose.y_m, 5),
        "heading_deg": round(math.degrees(pose.yaw_rad), 5),
        "sigma_x_m": round(sx, 6),
        "sigma_y_m": round(sy, 6),
        "sigma_heading_deg": round(math.degrees(syaw), 6),
    }


def point_json(point: TrackPoint, first_s: float) -> dict[str, Any]:
    e = point.estimate
    return {
        "kind": "estimate",
        "t_s": point.t_s,
        "elapsed_s": round(point.t_s - first_s, 6),
        "scanner": point.scanner,
        "scan_counter": point.scan_counter,
        "status": e.status.value,
        "reason": e.reason,
        "quality": e.quality,
        "measurement_t_s": e.t_s,
        "centre": _pose_sigma_json(e.centre_pose, e.centre_covariance),
        "scanners_midpoint": _pose_sigma_json(e.pose, e.covariance),
        "nis": {kind: round(value, 4) for kind, value in sorted(e.nis.items())},
        "accepted": dict(sorted(e.accepted.items())),
        "rejected": dict(sorted(e.rejected.items())),
    }


def point_text(point: TrackPoint, first_s: float) -> str:
    e = point.estimate
    head = f"{point.t_s - first_s:8.3f} s {point.scanner:<5} {e.status.value:<8} q{e.quality:3d}"
    centre = _pose_sigma_json(e.centre_pose, e.centre_covariance)
    if centre is None:
        return f"{head}  no pose: {e.reason}"
    nis = " ".join(f"{kind} {value:.2f}" for kind, value in sorted(e.nis.items())) or "-"
    reason = f"  ({e.reason})" if e.reason else ""
    return (
        f"{head}  x {centre['x_m']:+8.3f} ± {centre['sigma_x_m'] * 1e3:4.1f} mm  "
        f"y {centre['y_m']:+7.3f} ± {centre['sigma_y_m'] * 1e3:4.1f} mm  "
        f"heading {centre['heading_deg']:+6.2f} ± {centre['sigma_heading_deg']:.2f}°  "
        f"NIS {nis}  accepted {sum(e.accepted.values())} rejected {sum(e.rejected.values())}"
        f"{reason}"
    )


def recording_json(recording: RecordedScans) -> dict[str, Any]:
    return {
        "file": recording.path,
        "scans": len(recording.scans),
        "dropped_telegrams": recording.dropped_telegrams,
        "truncated": recording.truncated,
        "serial_numbers": sorted({scan.serial_number for scan in recording.scans}),
    }


def track_summary(track: Sequence[TrackPoint]) -> dict[str, Any]:
    """How many scans, how long in each status, when the first pose came, the last one."""
    first_s, last_s = track[0].t_s, track[-1].t_s
    time_s = dict.fromkeys(STATUSES, 0.0)
    for point, after in itertools.pairwise(track):
        time_s[point.estimate.status.value] += after.t_s - point.t_s
    first_pose = next((p for p in track if p.estimate.centre_pose is not None), None)
    return {
        "scans": len(track),
        "scans_by_scanner": {name: sum(p.scanner == name for p in track) for name in SCANNERS},
        "duration_s": round(last_s - first_s, 6),
        "time_s": {status: round(value, 6) for status, value in time_s.items()},
        "first_pose_t_s": first_pose.t_s if first_pose is not None else None,
        "first_pose_after_s": (
            round(first_pose.t_s - first_s, 6) if first_pose is not None else None
        ),
        "final": point_json(track[-1], first_s),
    }


def summary_text(summary: Mapping[str, Any]) -> str:
    by_scanner = ", ".join(f"{k} {v}" for k, v in summary["scans_by_scanner"].items())
    time_s = summary["time_s"]
    lines = [
        f"{summary['scans']} scans ({by_scanner}) over {summary['duration_s']:.3f} s, "
        f"{summary['stale_scans']} too old to use; vehicle {summary['vehicle']}, "
        f"{summary['site']}, poses of the vehicle centre in the launcher frame",
        "time " + ", ".join(f"{status} {time_s[status]:.3f} s" for status in STATUSES),
    ]
    if summary["first_pose_t_s"] is None:
        lines.append("no pose at all")
    else:
        lines.append(
            f"first pose at t={summary['first_pose_t_s']:.3f} s "
            f"({summary['first_pose_after_s']:.3f} s after the first scan)"
        )
    final = summary["final"]
    centre = final["centre"]
    reason = f" ({final['reason']})" if final["reason"] else ""
    if centre is None:
        lines.append(f"final: {final['status']}{reason}, no pose")
    else:
        lines.append(
            f"final: {final['status']}{reason}, quality {final['quality']}, centre "
            f"x {centre['x_m']:+.3f} m ± {centre['sigma_x_m'] * 1e3:.1f} mm, "
            f"y {centre['y_m']:+.3f} m ± {centre['sigma_y_m'] * 1e3:.1f} mm, "
            f"heading {centre['heading_deg']:+.2f}° ± {centre['sigma_heading_deg']:.2f}°"
        )
    if summary["png"]:
        lines.append(f"drew {summary['png']}")
    return "\n".join(lines)


# ---- drawing -------------------------------------------------------------------------
def draw_track(
    plt: Any,
    track: Sequence[TrackPoint],
    launcher: LauncherMap,
    config: VehicleConfig,
    title: str,
) -> Any:
    """Qian et al.'s Fig. 9: the centre's track in the launcher frame with the launcher
    drawn (2σ ellipses and heading arrows along it, the vehicle's outline at the last
    pose), and x, y and heading over time with ±2σ bands; lost and degraded spans shaded."""
    import numpy as np
    from matplotlib.patches import Ellipse, Polygon

    figure = plt.figure(figsize=(13, 9))
    grid = figure.add_gridspec(2, 3, height_ratios=(1.4, 1.0))
    plan = figure.add_subplot(grid[0, :])
    series = [figure.add_subplot(grid[1, k]) for k in range(3)]
    _draw_launcher(plt, plan, launcher)

    posed = [p for p in track if p.estimate.centre_pose is not None]
    first_s = track[0].t_s
    colours = {"ok": "tab:green", "degraded": "tab:orange", "lost": "tab:red"}
    if posed:
        poses = np.array([p.estimate.centre_pose for p in posed])
        covs = np.array([p.estimate.centre_covariance for p in posed])
        t = np.array([p.t_s - first_s for p in posed])
        plan.plot(poses[:, 0], poses[:, 1], color="tab:blue", linewidth=1, label="centre")
        for status, colour in colours.items():
            mask = np.array([p.estimate.status.value == status for p in posed])
            if mask.any():
                plan.scatter(poses[mask, 0], poses[mask, 1], s=6, color=colour, label=status)
        every = max(1, len(posed) // ELLIPSES_DRAWN)
        for k in range(0, len(posed), every):
            width, height, angle = _ellipse_2sigma(covs[k][:2, :2])
            plan.add_patch(
                Ellipse(
                    (poses[k, 0], poses[k, 1]), width, height, angle=angle,
                    fill=False, color="tab:blue", linewidth=0.8,
                )
            )  # fmt: skip
        arrow_m = 0.6
        picked = poses[::every]
        plan.quiver(
            picked[:, 0], picked[:, 1],
            arrow_m * np.cos(picked[:, 2]), arrow_m * np.sin(picked[:, 2]),
            angles="xy", scale_units="xy", scale=1.0, width=0.002, color="tab:blue",
        )  # fmt: skip
        outline = _outline(poses[-1], config.geometry.length_m, config.geometry.width_m)
        plan.add_patch(Polygon(outline, closed=True, fill=False, color="grey", linestyle="--"))
        sigmas = np.sqrt(np.maximum(np.array([np.diag(c) for c in covs]), 0.0))
        for axes, values, sigma, label in (
            (series[0], poses[:, 0], sigmas[:, 0], "x (m)"),
            (series[1], poses[:, 1], sigmas[:, 1], "y (m)"),
            (series[2], np.degrees(poses[:, 2]), np.degrees(sigmas[:, 2]), "heading (°)"),
        ):
            axes.fill_between(
                t, values - 2 * sigma, values + 2 * sigma, color="tab:blue", alpha=0.25,
                linewidth=0, label="±2σ",
            )  # fmt: skip
            axes.plot(t, values, color="tab:blue", linewidth=1)
            axes.set_ylabel(label)
            axes.set_xlabel("time (s) since the first scan")
            axes.grid(True, linewidth=0.3)
    for axes in series:
        _shade_status(axes, track, first_s, colours)
    series[2].legend(loc="best", fontsize="small")
    plan.set_aspect("equal", adjustable="datalim")
    plan.set_xlabel("x (m), launcher frame")
    plan.set_ylabel("y (m)")
    plan.grid(True, linewidth=0.3)
    plan.legend(loc="upper left", fontsize="small", markerscale=2)
    plan.set_title(f"{title}\nthe vehicle centre's track (2σ ellipses, heading arrows)")
    figure.tight_layout()
    return figure


def _draw_launcher(plt: Any, axes: Any, launcher: LauncherMap) -> None:
    half = launcher.half_width_m
    axes.plot([0.0, 0.0], [-half, half], color="black", linewidth=2.5, label="launcher")
    for side in (1.0, -1.0):
        far_x, far_y = launcher.side_board_far_end(side)
        axes.plot([0.0, far_x], [side * half, far_y], color="black", linewidth=2.5)
    for cylinder in launcher.cylinders:
        axes.add_patch(plt.Circle((cylinder.x_m, cylinder.y_m), cylinder.radius_m, color="black"))


def _ellipse_2sigma(covariance: Any) -> tuple[float, float, float]:
    """Width, height (m) and angle (°) of the 2σ ellipse of a 2x2 position covariance."""
    import numpy as np

    values, vectors = np.linalg.eigh(np.asarray(covariance, dtype=float))
    values = np.maximum(values, 0.0)
    angle = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1]))
    return 4.0 * math.sqrt(values[1]), 4.0 * math.sqrt(values[0]), angle  # major along angle


def _outline(pose: Any, length_m: float, width_m: float) -> list[tuple[float, float]]:
    x, y, yaw = (float(v) for v in pose)
    c, s = math.cos(yaw), math.sin(yaw)
    corners = [(length_m / 2, width_m / 2), (-length_m / 2, width_m / 2)]
    corners += [(-length_m / 2, -width_m / 2), (length_m / 2, -width_m / 2)]
    return [(x + c * dx - s * dy, y + s * dx + c * dy) for dx, dy in corners]


def _shade_status(
    axes: Any, track: Sequence[TrackPoint], first_s: float, colours: Mapping[str, str]
) -> None:
    """Shade each span the estimate was degraded or lost."""
    start = 0
    for k in range(1, len(track) + 1):
        status = track[start].estimate.status.value
        if k < len(track) and track[k].estimate.status.value == status:
            continue
        if status != "ok":
            end_s = track[k].t_s if k < len(track) else track[-1].t_s
            axes.axvspan(
                track[start].t_s - first_s, end_s - first_s, color=colours[status], alpha=0.15
            )
        start = k
