"""What a consumer 3D LiDAR terminal gets wrong about where it is, drawn from a seed.

Kinouchi et al.: the worker's terminal is "not for industrial use": its map is off by a
few centimetres and a small heading, and in the paper's trial n = 2 notably more. Where
that error comes from is modelled in two parts, both in the plane: the terminal's
estimate of the floor marker that defines its map frame W, and its tracking (odometry)
as the worker walks from the marker from viewpoint to viewpoint. Heights are not in
error: AR terminals align their map's z with gravity, so the floor stays at z = 0.

The marker's surveyed pose ``marker`` is exact (the marker is where it was surveyed); the
terminal's estimate of it is not, so W's true pose in the site is

    t0_true = marker ∘ marker_error

(``Pose2D.compose``: the error is expressed in the marker's own frame), while the vehicle,
like the terminal, believes W is the marker: its T0 is ``marker``.

The model (`TerminalErrors`; the figures are ours, the paper gives none):

- marker error: x, y each Gaussian with ``marker_xy_sigma_m``, yaw Gaussian with
  ``marker_yaw_sigma_rad``, drawn once per survey;
- odometry (the terminal's tracking between viewpoints, starting where it photographed
  the marker, taken as the marker's position): a scale error drawn once (Gaussian,
  ``odometry_scale_sigma``), and per leg of length L between consecutive viewpoints a
  random walk in position (each axis sigma ``position_walk_m_per_sqrt_m`` x sqrt(L)) and
  heading (sigma ``heading_walk_rad_per_sqrt_m`` x sqrt(L)). Legs are composed in the
  previous *believed* pose, so a heading error turns later legs and grows into a position
  error, as a real tracker's does;
- the object-list form of a worker map (``object_*_sigma``): the terminal's own fit of
  each object's pose, on top of the marker error and drift of the viewpoint it was
  measured from.

All draws come from the caller's ``numpy.random.Generator`` in a fixed order (marker: 3,
scale: 1, legs: 3 each), always as many whatever the preset: one seed gives the same
standard draws to IDEAL, CONSUMER and WORSE, whose errors are then scaled copies of each
other, and a survey and an object survey of one seed and walk share their marker error
and drift.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from appliance.mapping.pallets import inverse_pose
from drivers.geometry import Pose2D

_FULL_TURN_RAD = 2.0 * math.pi

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TerminalErrors:
    """A terminal's error magnitudes (1 sigma); see the module doc for the model."""

    marker_xy_sigma_m: float
    marker_yaw_sigma_rad: float
    odometry_scale_sigma: float
    position_walk_m_per_sqrt_m: float
    heading_walk_rad_per_sqrt_m: float
    # For the object-list form of a worker map (`survey_objects`): the terminal's own
    # fit of each object's pose, on top of the marker and odometry errors.
    object_xy_sigma_m: float
    object_yaw_sigma_rad: float

    def __post_init__(self) -> None:
        values = (
            self.marker_xy_sigma_m,
            self.marker_yaw_sigma_rad,
            self.odometry_scale_sigma,
            self.position_walk_m_per_sqrt_m,
            self.heading_walk_rad_per_sqrt_m,
            self.object_xy_sigma_m,
            self.object_yaw_sigma_rad,
        )
        if not all(math.isfinite(v) and v >= 0.0 for v in values):
            raise ValueError(f"terminal error sigmas must be finite and >= 0: {self}")

    def scaled(self, factor: float) -> TerminalErrors:
        """Every sigma times ``factor``."""
        return TerminalErrors(
            self.marker_xy_sigma_m * factor,
            self.marker_yaw_sigma_rad * factor,
            self.odometry_scale_sigma * factor,
            self.position_walk_m_per_sqrt_m * factor,
            self.heading_walk_rad_per_sqrt_m * factor,
            self.object_xy_sigma_m * factor,
            self.object_yaw_sigma_rad * factor,
        )


# A consumer tablet, typical (ours): the marker photographed from a metre or two gives
# its position to ~2 cm and its direction to ~0.3 deg; tracking drifts 0.5 % in scale
# and, per 10 m walked, ~1.6 cm and 0.3 deg of random walk. On the `pallets` site's
# 43 m `walk_around` route a pallet ends up, through T0 = the marker, a median 6 cm
# (95 %: 13 cm) and 0.4 deg (95 %: 1.2 deg) from where it is: "a few centimetres".
# Walking 30 m straight away from the marker, the drift alone is ~18 cm (0.6 %).
CONSUMER = TerminalErrors(
    marker_xy_sigma_m=0.02,
    marker_yaw_sigma_rad=math.radians(0.3),
    odometry_scale_sigma=0.005,
    position_walk_m_per_sqrt_m=0.005,
    heading_walk_rad_per_sqrt_m=math.radians(0.3) / math.sqrt(10.0),
    object_xy_sigma_m=0.01,
    object_yaw_sigma_rad=math.radians(0.3),
)
# The paper's trial n = 2, where the worker's map was notably worse: every sigma 2.5x
# (on the same route: median 15 cm and 1 deg, 95 %: 33 cm and 3 deg).
WORSE = CONSUMER.scaled(2.5)
IDEAL = CONSUMER.scaled(0.0)  # no error at all: the worker frame is the marker's


class TerminalWalk(NamedTuple):
    """The marker error, W's true pose in the site, and each viewpoint's pose in W."""

    marker_error: Pose2D
    t0_true: Pose2D
    true_w: tuple[Pose2D, ...]  # each viewpoint's true pose in W
    believed_w: tuple[Pose2D, ...]  # the terminal's belief of it
    walked_m: FloatArray


def draw_walk(
    marker: Pose2D, viewpoints: Sequence[Pose2D], errors: TerminalErrors, rng: np.random.Generator
) -> TerminalWalk:
    """The marker error and the odometry's belief of each of ``viewpoints`` (site frame,
    in walking order), as the module doc models them; draws 4 + 3 x viewpoints normals."""
    unit = rng.standard_normal(4 + 3 * len(viewpoints))
    marker_error = Pose2D(
        errors.marker_xy_sigma_m * float(unit[0]),
        errors.marker_xy_sigma_m * float(unit[1]),
        errors.marker_yaw_sigma_rad * float(unit[2]),
    )
    scale = 1.0 + errors.odometry_scale_sigma * float(unit[3])
    t0_true = marker.compose(marker_error)
    to_w = inverse_pose(t0_true)
    # Tracking starts at the photo of the marker, where the belief is the truth (W is
    # defined by that photo): the marker's own pose in W.
    previous, believed, walked = marker, inverse_pose(marker_error), 0.0
    true_w: list[Pose2D] = []
    believed_w: list[Pose2D] = []
    walked_m: list[float] = []
    for k, viewpoint in enumerate(viewpoints):
        leg = inverse_pose(previous).compose(viewpoint)
        length_m = math.hypot(leg.x_m, leg.y_m)
        root = math.sqrt(length_m)
        nx, ny, nyaw = (float(v) for v in unit[4 + 3 * k : 7 + 3 * k])
        measured = Pose2D(
            scale * leg.x_m + errors.position_walk_m_per_sqrt_m * root * nx,
            scale * leg.y_m + errors.position_walk_m_per_sqrt_m * root * ny,
            leg.yaw_rad + errors.heading_walk_rad_per_sqrt_m * root * nyaw,
        )
        believed = wrapped(believed.compose(measured))
        walked += length_m
        true_w.append(wrapped(to_w.compose(viewpoint)))
        believed_w.append(believed)
        walked_m.append(walked)
        previous = viewpoint
    return TerminalWalk(marker_error, t0_true, tuple(true_w), tuple(believed_w), np.array(walked_m))


def wrapped(pose: Pose2D) -> Pose2D:
    """``pose`` with its yaw in [-pi, pi): composing poses adds yaws without bound."""
    return Pose2D(pose.x_m, pose.y_m, wrap_rad(pose.yaw_rad))


def wrap_rad(angle_rad: float) -> float:
    """``angle_rad`` in [-pi, pi)."""
    return (angle_rad + math.pi) % _FULL_TURN_RAD - math.pi
