"""The last straight into a pallet, from where the vehicle sees it: the math.

**Frame.** Everything is measured in the entry face's frame (``EntryFace.frame``:
origin at the face's centre, x into the pallet, y to the left), from the pallet as
*detected*, not as mapped: the detection reaches the site frame through the vehicle's
estimate, so an offset of the estimate moves both alike and cancels in their
difference (a heading error leaves a drift along the way, which `DetectionFilter`
takes out); the worker's map's error does not enter at all.

**Kinematics.** The rear axle steers, so the point that moves along the vehicle's
heading is the middle of the *front* axle (the guide point). With ``x`` along the
face's axis, ``e`` the guide point's lateral offset and ``ψ`` the heading relative to
the axis, for an effective steering angle ``δ`` (positive left):

    ẋ = v cos ψ,   ė = v sin ψ,   ψ̇ = v tan δ / L,

the equations of a front-steered car's *rear* axle. With distance along the axis as
the independent variable, ``e' = tan ψ`` and ``(tan ψ)' = κ / cos³ψ`` (``κ = tan δ / L``),
so the curvature law

    κ = cos³ψ · (y_r'' − k_e (e − y_r) − k_ψ (tan ψ − y_r'))

makes the error from a reference ``y_r(x)`` obey, exactly (not only near the axis),
``z'' + k_ψ z' + k_e z = 0``: a linear second-order system in distance, whatever the
speed. ``k_ψ = 2 / ℓ``, ``k_e = 1 / ℓ²`` is critically damped, the error shrinking as
``(1 + s/ℓ) e^(−s/ℓ)`` over ``s`` metres driven; ``ℓ`` is a fraction of a metre. A
point offset sideways on the vehicle (the forks' centre line, when a side shifter moves
it) also moves along the heading, so the same law holds for it.

**Reference.** Rather than asking the law to null the whole offset found at the view
pose (it would saturate the steering, and end still converging), the reference is
re-planned from the detection: a quintic ``y_r(x)`` from the guide point's offset and
heading where it stands (and zero curvature) to the axis with zero slope and curvature,
``settle`` metres before the tips reach the face, then the axis itself. The error from
it starts at zero; what is left to the law is the actuator's lag and the noise. A
quintic whose curvature exceeds what the vehicle may use is refused: the pallet is
then too far off the line the vehicle stands on, and a new view pose is needed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.guidance.pallet_geometry import EntryFace
from appliance.mapping.pallets import Pallet, PalletKind, posture_difference_rad
from drivers.geometry import Pose2D


@dataclass(frozen=True)
class LateralReference:
    """``y_r(x)`` for ``x`` from ``x0_m`` to ``x1_m`` (a quintic), zero beyond; before
    ``x0_m``, its first value."""

    x0_m: float
    x1_m: float
    coefficients: tuple[float, float, float, float, float, float]  # in τ = (x−x0)/(x1−x0)

    def curvature_rate_per_m2(self, x_m: float) -> float:
        """``|d³y_r/dx³|`` at ``x_m``: how fast the reference's curvature changes with
        distance (what the steering's rate limit has to keep up with)."""
        span = self.x1_m - self.x0_m
        if x_m >= self.x1_m or span <= 0.0:
            return 0.0
        tau = max(0.0, (x_m - self.x0_m) / span)
        _, _, _, a3, a4, a5 = self.coefficients
        return abs(6 * a3 + tau * (24 * a4 + tau * 60 * a5)) / span**3

    def at(self, x_m: float) -> tuple[float, float, float]:
        """``y_r``, ``dy_r/dx`` and ``d²y_r/dx²`` at ``x_m``."""
        span = self.x1_m - self.x0_m
        if x_m >= self.x1_m or span <= 0.0:
            return 0.0, 0.0, 0.0
        tau = max(0.0, (x_m - self.x0_m) / span)
        a0, a1, a2, a3, a4, a5 = self.coefficients
        y = a0 + tau * (a1 + tau * (a2 + tau * (a3 + tau * (a4 + tau * a5))))
        dy = a1 + tau * (2 * a2 + tau * (3 * a3 + tau * (4 * a4 + tau * 5 * a5)))
        ddy = 2 * a2 + tau * (6 * a3 + tau * (12 * a4 + tau * 20 * a5))
        return y, dy / span, ddy / (span * span)

    def max_curvature_per_m(self, samples: int = 64) -> float:
        """The largest ``|y_r''|``: the curvature the reference asks for (a bound on it,
        ``cos³ψ ≤ 1``)."""
        span = self.x1_m - self.x0_m
        return max(abs(self.at(self.x0_m + span * i / samples)[2]) for i in range(samples))

    def max_slope(self, samples: int = 64) -> float:
        span = self.x1_m - self.x0_m
        return max(abs(self.at(self.x0_m + span * i / samples)[1]) for i in range(samples))


def lateral_reference(
    x0_m: float, lateral_m: float, heading_rad: float, x1_m: float
) -> LateralReference:
    """The quintic from ``(lateral, tan heading, 0)`` at ``x0`` to ``(0, 0, 0)`` at ``x1``:
    with ``A = −e − m``, ``B = −m`` (``m`` the slope in τ), ``a3 = 10A − 4B``,
    ``a4 = −15A + 7B``, ``a5 = 6A − 3B`` meet the three end conditions."""
    span = x1_m - x0_m
    slope = math.tan(heading_rad) * span
    a = -lateral_m - slope
    b = -slope
    return LateralReference(
        x0_m,
        x1_m,
        (lateral_m, slope, 0.0, 10 * a - 4 * b, -15 * a + 7 * b, 6 * a - 3 * b),
    )


def curvature_wish_per_m(
    lateral_m: float,
    heading_rad: float,
    reference: tuple[float, float, float],
    convergence_length_m: float,
) -> float:
    """The module docstring's law: the curvature that brings ``(e, tan ψ)`` onto the
    reference ``(y_r, y_r', y_r'')`` critically damped over ``convergence_length_m``."""
    y_r, slope_r, curvature_r = reference
    k_e = 1.0 / convergence_length_m**2
    k_psi = 2.0 / convergence_length_m
    u = curvature_r - k_e * (lateral_m - y_r) - k_psi * (math.tan(heading_rad) - slope_r)
    return math.cos(heading_rad) ** 3 * u


@dataclass(frozen=True)
class FaceErrors:
    """The vehicle against an entry face, in the face's frame."""

    guide_along_m: float  # the guide point's x (negative: before the face)
    guide_lateral_m: float  # the forks' centre line at the guide point, left of the axis
    heading_rad: float  # the vehicle's heading against the entry direction
    tips_lateral_m: float  # the forks' centre line at the tips, left of the axis
    tips_along_m: float  # the tips' x: 0 at the face


def face_errors(
    centre: Pose2D,
    face: EntryFace,
    guide_forward_m: float,
    tips_forward_m: float,
    forks_offset_y_m: float,
) -> FaceErrors:
    frame = face.frame()
    c, s = math.cos(frame.yaw_rad), math.sin(frame.yaw_rad)

    def local(x_m: float, y_m: float) -> tuple[float, float]:
        dx, dy = x_m - frame.x_m, y_m - frame.y_m
        return c * dx + s * dy, -s * dx + c * dy

    guide = local(*centre.apply(guide_forward_m, forks_offset_y_m))
    tips = local(*centre.apply(tips_forward_m, forks_offset_y_m))
    heading = math.remainder(centre.yaw_rad - frame.yaw_rad, math.tau)
    return FaceErrors(guide[0], guide[1], heading, tips[1], tips[0])


class DetectionFilter:
    """The target as detected, fused over the approach.

    A detection reaches the site frame through the pose estimate of its moment, and an
    estimate whose heading is off by ``ε`` moves a detected pallet sideways by about
    ``ε`` per metre the vehicle drives (the position error turns with the vehicle's
    displacement; a heading error of 0.5° is 9 mm per metre). Each detection is right
    *with the estimate of its own moment*, so a plain mean over the approach lags
    behind, and a short one is noisy. So the position is fitted as a line in the
    distance the vehicle has driven, ``p(s) = p̄ + b (s − s̄)`` (exponentially weighted
    least squares, ``memory`` per detection; the slope shrunk toward 0 by a prior
    spread ``slope_prior_m`` so that standing still it is the mean), and read at the
    vehicle's present ``s``. The yaw does not drift that way (a heading error adds a
    constant to it): its weighted mean, on one branch of the footprint's symmetry.
    Equal weights: the detections come from the same scanners at about the same range.
    """

    def __init__(self, memory: float, slope_prior_m: float) -> None:
        self.memory = memory
        self.slope_prior_m = slope_prior_m
        self.reset()

    def reset(self) -> None:
        self.count = 0
        self._kind: PalletKind | None = None
        self._name = ""
        self._origin = (0.0, 0.0, 0.0, 0.0)  # the first detection's x, y, yaw and s
        # Weighted sums of 1, s, s², x, y, x s, y s, yaw (relative to the origin).
        self._sums = [0.0] * 8

    def pallet_at(self, travelled_m: float) -> Pallet | None:
        """The fused pallet for the vehicle having driven ``travelled_m``."""
        if self._kind is None:
            return None
        w, ws, wss, wx, wy, wxs, wys, wyaw = self._sums
        x0, y0, yaw0, s0 = self._origin
        mean_s, mean_x, mean_y = ws / w, wx / w, wy / w
        spread = max(0.0, wss / w - mean_s * mean_s) + self.slope_prior_m**2
        slope_x = (wxs / w - mean_x * mean_s) / spread
        slope_y = (wys / w - mean_y * mean_s) / spread
        ahead = (travelled_m - s0) - mean_s
        return Pallet(
            x0 + mean_x + slope_x * ahead,
            y0 + mean_y + slope_y * ahead,
            yaw0 + wyaw / w,
            np.zeros((3, 3)),
            self._kind,
            self._name,
        )

    def distance_to(self, pallet: Pallet, travelled_m: float) -> tuple[float, float]:
        """Position and posture distance of ``pallet`` from the fused one (inf without)."""
        fused = self.pallet_at(travelled_m)
        if fused is None:
            return math.inf, math.inf
        return math.hypot(pallet.x_m - fused.x_m, pallet.y_m - fused.y_m), abs(
            posture_difference_rad(pallet.yaw_rad, fused.yaw_rad, pallet.kind.symmetry_rad)
        )

    def add(self, pallet: Pallet, travelled_m: float) -> None:
        if self._kind is None:
            self._kind, self._name = pallet.kind, pallet.name
            self._origin = (pallet.x_m, pallet.y_m, pallet.yaw_rad, travelled_m)
        x0, y0, yaw0, s0 = self._origin
        x, y, s = pallet.x_m - x0, pallet.y_m - y0, travelled_m - s0
        yaw = posture_difference_rad(pallet.yaw_rad, yaw0, pallet.kind.symmetry_rad)
        fresh = (1.0, s, s * s, x, y, x * s, y * s, yaw)
        self._sums = [self.memory * old + new for old, new in zip(self._sums, fresh, strict=True)]
        self.count += 1
