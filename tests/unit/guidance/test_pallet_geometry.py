"""The pallet planner's geometry: Dubins paths, faces, the overlap test, scanner fields."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from appliance.guidance.arc_paths import (
    PathPiece,
    dubins_length_m,
    dubins_paths,
    pose_after,
    sample_pieces,
)
from appliance.guidance.pallet_geometry import (
    Obstacle,
    ScannerField,
    entry_face,
    face_in_view,
    nearest_entry_face,
    overlaps,
    pallet_obstacle,
    rectangle_corners,
    view_pose,
)
from appliance.mapping.pallets import Pallet, PalletKind
from drivers.geometry import Pose2D
from tests.unit.guidance.pallet_scene import vehicle_shape

coordinate = st.floats(-20.0, 20.0)
angle = st.floats(-4.0, 4.0)


@given(coordinate, coordinate, angle, coordinate, coordinate, angle, st.floats(0.3, 5.0))
# A goal 6e-8 m straight ahead: rounding turns words into empty paths (RLR's full loop
# into none), which land within the 1e-6 m every path is held to, as they should; the
# shortest path may be that much shorter than the way there, not more.
@example(-5.960464477539063e-08, -5.960464477539063e-08, 0.0, 0.0, -5.960464477539063e-08, 0.0, 3.0)
def test_every_dubins_word_ends_at_the_goal(
    x0: float, y0: float, a0: float, x1: float, y1: float, a1: float, radius: float
) -> None:
    start, goal = Pose2D(x0, y0, a0), Pose2D(x1, y1, a1)
    paths = dubins_paths(start, goal, radius)
    assert paths  # forward paths always exist in the open plane
    for pieces in paths:
        pose = start
        for piece in pieces:
            assert abs(piece.curvature_per_m) <= 1.0 / radius + 1e-12
            assert piece.length_m > 0.0
            pose = pose_after(pose, piece)
        assert math.hypot(pose.x_m - x1, pose.y_m - y1) < 1e-6
        assert abs(math.remainder(pose.yaw_rad - a1, math.tau)) < 1e-6
    lengths = [sum(p.length_m for p in pieces) for pieces in paths]
    assert all(a <= b + 1e-9 for a, b in itertools.pairwise(lengths))
    assert lengths[0] >= math.hypot(x1 - x0, y1 - y0) - 1e-6


def test_dubins_straight_ahead_is_the_distance_and_behind_is_a_loop() -> None:
    assert dubins_length_m(Pose2D(0, 0, 0), Pose2D(7, 0, 0), 1.0) == pytest.approx(7.0)
    # A goal right behind, facing the same way: a full turn's worth at least.
    assert dubins_length_m(Pose2D(0, 0, 0), Pose2D(-1, 0, 0), 1.0) > 2 * math.pi


def test_sampled_pieces_follow_the_arcs() -> None:
    pieces = (PathPiece(0.5, 2 * math.pi), PathPiece(0.0, 1.0))  # half a turn, radius 2
    poses, curvature, arc = sample_pieces(Pose2D(0.0, 0.0, 0.0), pieces, 0.05)
    assert arc[-1] == pytest.approx(2 * math.pi + 1.0)
    assert poses[-1] == pytest.approx([-1.0, 4.0, math.pi])
    on_arc = arc <= 2 * math.pi
    assert np.hypot(poses[on_arc, 0], poses[on_arc, 1] - 2.0) == pytest.approx(2.0)
    assert curvature[1:][arc[1:] <= 2 * math.pi] == pytest.approx(0.5)


def test_a_eur_pallet_is_entered_along_its_length_a_jis_pallet_from_any_side() -> None:
    eur = Pallet(1.0, 2.0, 0.5, np.zeros((3, 3)), PalletKind.EUR)
    face = entry_face(eur, 0)
    assert face.half_span_m == pytest.approx(0.4)  # the short (800 mm) face
    assert face.depth_m == pytest.approx(0.6)
    assert (face.centre_x_m, face.centre_y_m) == pytest.approx(
        (1.0 + 0.6 * math.cos(0.5), 2.0 + 0.6 * math.sin(0.5))
    )
    assert math.remainder(face.entry_yaw_rad - (0.5 + math.pi), math.tau) == pytest.approx(0.0)
    # Re-detected half a turn round (its yaw is only known up to its symmetry), the face
    # nearest the plan's entry direction is the same side.
    turned = Pallet(1.0, 2.0, 0.5 + math.pi, np.zeros((3, 3)), PalletKind.EUR)
    again = nearest_entry_face(turned, face.entry_yaw_rad)
    assert (again.centre_x_m, again.centre_y_m) == pytest.approx((face.centre_x_m, face.centre_y_m))
    jis = Pallet(0.0, 0.0, 0.0, np.zeros((3, 3)), PalletKind.JIS)
    sides = [nearest_entry_face(jis, a) for a in (0.0, math.pi / 2, math.pi, -math.pi / 2)]
    assert len({(round(f.centre_x_m, 6), round(f.centre_y_m, 6)) for f in sides}) == 4


def test_the_view_pose_puts_the_tips_the_standoff_before_the_face_centre() -> None:
    shape = vehicle_shape()
    face = entry_face(Pallet(5.0, 1.0, 0.2, np.zeros((3, 3)), PalletKind.EUR), 2)
    view = view_pose(shape, face, 1.5)
    tips = view.compose(Pose2D(shape.tips_forward_m, 0.0, 0.0))
    frame = face.frame()
    assert tips.yaw_rad == pytest.approx(frame.yaw_rad)
    assert (tips.x_m, tips.y_m) == pytest.approx(frame.apply(-1.5, 0.0))
    assert face_in_view(shape, view, face) == ""
    # Turned away, or too close for the scanners at the front corners: not seen.
    assert face_in_view(shape, view.compose(Pose2D(0, 0, math.pi)), face) != ""
    blind = ScannerField(Pose2D(0.85, 0.55, math.radians(45.0)), math.radians(30.0))
    narrow = type(shape)(**{**shape.__dict__, "scanners": (blind,)})
    assert "does not see" in face_in_view(narrow, view, face)


def test_a_pallet_grows_by_its_uncertainty_and_the_clearance() -> None:
    covariance = np.diag([0.04**2, 0.01**2, 0.0])
    grown = pallet_obstacle(Pallet(0.0, 0.0, 0.0, covariance, PalletKind.EUR), 3.0, 0.2)
    xs, ys = grown.corners_xy_m[:, 0], grown.corners_xy_m[:, 1]
    assert xs.max() == pytest.approx(0.6 + 0.12 + 0.2)
    assert ys.max() == pytest.approx(0.4 + 0.12 + 0.2)


@given(st.floats(-3, 3), st.floats(-3, 3), angle, st.floats(0.1, 2), st.floats(0.1, 2), angle)
def test_overlap_agrees_with_sampling(
    x: float, y: float, yaw: float, half_l: float, half_w: float, other_yaw: float
) -> None:
    """The separating-axis test against points sampled over both rectangles."""
    a = rectangle_corners(Pose2D(x, y, yaw), half_l, half_w)
    b = rectangle_corners(Pose2D(0.0, 0.0, other_yaw), 1.0, 0.5)
    exact = bool(overlaps(a[None], Obstacle("b", b))[0])

    def grid(pose: Pose2D, hl: float, hw: float) -> np.ndarray:
        u, v = np.meshgrid(np.linspace(-hl, hl, 60), np.linspace(-hw, hw, 60))
        return np.array([pose.apply(p, q) for p, q in zip(u.ravel(), v.ravel(), strict=True)])

    def inside(points: np.ndarray, pose: Pose2D, hl: float, hw: float) -> np.ndarray:
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        dx, dy = points[:, 0] - pose.x_m, points[:, 1] - pose.y_m
        return (np.abs(c * dx + s * dy) < hl) & (np.abs(-s * dx + c * dy) < hw)

    pa, pb = Pose2D(x, y, yaw), Pose2D(0.0, 0.0, other_yaw)
    sampled = bool(
        inside(grid(pa, half_l, half_w), pb, 1.0, 0.5).any()
        or inside(grid(pb, 1.0, 0.5), pa, half_l, half_w).any()
    )
    if sampled:
        assert exact  # sampling only finds true overlaps
    if exact and not sampled:
        # A sliver thinner than the sampling: shrinking a little separates them.
        shrunk = rectangle_corners(pa, half_l * 0.95, half_w * 0.95)
        assert not overlaps(shrunk[None], Obstacle("b", rectangle_corners(pb, 0.95, 0.475)))[0]
