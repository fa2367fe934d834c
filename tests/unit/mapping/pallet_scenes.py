"""Scenes for the pallet detection tests, built without the code under test.

2D: rectangles (pallets, posts) seen from a viewpoint. A face is sampled at a regular
spacing with a random phase (as a scanner samples a surface), a point is kept when its
face's outward normal points towards the viewpoint and the segment from it to the
viewpoint crosses no other rectangle's face, and the range noise is added along the ray.

3D: a pallet as its parts (bottom boards, 3x3 blocks, a deck), each an axis-aligned box
in the pallet's frame whose surfaces are sampled uniformly at a density, plus a floor, a
cargo box on the deck, posts and legs; isotropic Gaussian noise on every point.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

DIMENSIONS_M = {"1200x800": (1.2, 0.8), "1100x1100": (1.1, 1.1)}


@dataclass(frozen=True)
class Rect:
    """A rectangle on the floor: centre, the direction of its length, its size."""

    x_m: float
    y_m: float
    yaw_rad: float
    length_m: float
    width_m: float

    def corners(self) -> FloatArray:
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        hl, hw = self.length_m / 2.0, self.width_m / 2.0
        local = np.array([(hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)])
        return local @ np.array([[c, s], [-s, c]]) + (self.x_m, self.y_m)

    def faces(self) -> list[tuple[FloatArray, FloatArray]]:
        """(start, end) of each side, counter-clockwise: the outward normal is to the right."""
        corners = self.corners()
        return [(corners[k], corners[(k + 1) % 4]) for k in range(4)]


def _crosses(p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray) -> bool:
    """Whether segment pq properly crosses segment ab."""

    def side(u: FloatArray, v: FloatArray, w: FloatArray) -> float:
        return float((v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0]))

    return side(p, q, a) * side(p, q, b) < 0.0 and side(a, b, p) * side(a, b, q) < 0.0


def outline(
    rects: list[Rect],
    index: int,
    viewpoint: tuple[float, float],
    spacing_m: float,
    sigma_m: float,
    rng: np.random.Generator,
) -> FloatArray:
    """The visible outline points of ``rects[index]`` with range noise ``sigma_m``."""
    view = np.asarray(viewpoint, dtype=float)
    points = []
    for start, end in rects[index].faces():
        edge = end - start
        length = float(np.hypot(*edge))
        outward = np.array([edge[1], -edge[0]]) / length
        phase = rng.uniform(0.0, spacing_m)
        for along in np.arange(phase, length, spacing_m):
            p = start + edge * (along / length)
            if outward @ (view - p) <= 0.0:
                continue
            others = (f for k, r in enumerate(rects) if k != index for f in r.faces())
            if any(_crosses(p, view, a, b) for a, b in others):
                continue
            points.append(p)
    xy = np.array(points).reshape(-1, 2)
    rays = xy - view
    rays /= np.hypot(rays[:, 0], rays[:, 1])[:, None]
    return xy + rays * rng.normal(0.0, sigma_m, (xy.shape[0], 1))


def polyline(
    corners: list[tuple[float, float]], spacing_m: float, sigma_m: float, seed: int
) -> FloatArray:
    """Points along a polyline (clutter: a wall, a shelf's corner) with range noise
    from the origin."""
    rng = np.random.default_rng(seed)
    pieces = []
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        n = max(2, int(math.hypot(x1 - x0, y1 - y0) / spacing_m))
        t = np.linspace(0.0, 1.0, n, endpoint=False)
        pieces.append(np.column_stack((x0 + t * (x1 - x0), y0 + t * (y1 - y0))))
    xy = np.concatenate(pieces)
    rays = xy / np.hypot(xy[:, 0], xy[:, 1])[:, None]
    return xy + rays * rng.normal(0.0, sigma_m, (xy.shape[0], 1))


def arc(centre: tuple[float, float], radius_m: float, span_rad: float, n: int) -> FloatArray:
    """Points on an arc facing the origin, without noise (a leg, a drum)."""
    angle = math.atan2(-centre[1], -centre[0]) + np.linspace(-span_rad / 2, span_rad / 2, n)
    return np.column_stack(
        (centre[0] + radius_m * np.cos(angle), centre[1] + radius_m * np.sin(angle))
    )


def pallet_rect(kind: str, x_m: float, y_m: float, yaw_rad: float) -> Rect:
    length, width = DIMENSIONS_M[kind]
    return Rect(x_m, y_m, yaw_rad, length, width)


# ---- 3D ----------------------------------------------------------------------------


def box_surface(
    low: tuple[float, float, float],
    high: tuple[float, float, float],
    density_per_m2: float,
    rng: np.random.Generator,
) -> FloatArray:
    """Points uniformly on the six faces of an axis-aligned box."""
    lo, hi = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    size = hi - lo
    chunks = []
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        area = size[others[0]] * size[others[1]]
        for level in (lo[axis], hi[axis]):
            count = int(rng.poisson(area * density_per_m2))
            pts = np.empty((count, 3))
            pts[:, axis] = level
            for k in others:
                pts[:, k] = rng.uniform(lo[k], hi[k], count)
            chunks.append(pts)
    return np.concatenate(chunks)


def pallet_boxes(length_m: float, width_m: float) -> list[tuple[tuple[float, ...], ...]]:
    """A block pallet in its own frame (x along the length, floor at z = 0): three
    bottom boards (0-22 mm), 3x3 blocks (22-100 mm), a deck (100-144 mm)."""
    hl, hw = length_m / 2.0, width_m / 2.0
    block_l, block_w = 0.145, 0.145
    boxes: list[tuple[tuple[float, ...], ...]] = []
    for yc in (-hw + block_w / 2.0, 0.0, hw - block_w / 2.0):
        boxes.append(((-hl, yc - block_w / 2.0, 0.0), (hl, yc + block_w / 2.0, 0.022)))
        for xc in (-hl + block_l / 2.0, 0.0, hl - block_l / 2.0):
            lo = (xc - block_l / 2.0, yc - block_w / 2.0, 0.022)
            boxes.append((lo, (xc + block_l / 2.0, yc + block_w / 2.0, 0.100)))
    boxes.append(((-hl, -hw, 0.100), (hl, hw, 0.144)))
    return boxes


def pallet_cloud(
    kind: str,
    x_m: float,
    y_m: float,
    yaw_rad: float,
    density_per_m2: float,
    rng: np.random.Generator,
    cargo: bool = True,
) -> FloatArray:
    """A pallet's surfaces (and a cargo box on its deck, overhanging nothing)."""
    length, width = DIMENSIONS_M[kind]
    boxes = pallet_boxes(length, width)
    local = np.concatenate([box_surface(lo, hi, density_per_m2, rng) for lo, hi in boxes])
    placed = _placed(local, x_m, y_m, yaw_rad)
    if cargo:
        placed = np.concatenate((placed, cargo_cloud(x_m, y_m, yaw_rad, density_per_m2, rng)))
    return placed


def cargo_cloud(
    x_m: float, y_m: float, yaw_rad: float, density_per_m2: float, rng: np.random.Generator
) -> FloatArray:
    """A 0.9 x 0.6 x 0.756 m box standing on a pallet's deck (0.144 m up)."""
    local = box_surface((-0.45, -0.3, 0.144), (0.45, 0.3, 0.9), density_per_m2, rng)
    return _placed(local, x_m, y_m, yaw_rad)


def _placed(local: FloatArray, x_m: float, y_m: float, yaw_rad: float) -> FloatArray:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    world = local.copy()
    world[:, 0] = x_m + c * local[:, 0] - s * local[:, 1]
    world[:, 1] = y_m + s * local[:, 0] + c * local[:, 1]
    return world


def floor_cloud(half_size_m: float, density_per_m2: float, rng: np.random.Generator) -> FloatArray:
    count = int(4.0 * half_size_m * half_size_m * density_per_m2)
    floor = np.zeros((count, 3))
    floor[:, :2] = rng.uniform(-half_size_m, half_size_m, (count, 2))
    return floor


def post_cloud(
    x_m: float, y_m: float, size_m: float, height_m: float, density: float, rng: np.random.Generator
) -> FloatArray:
    h = size_m / 2.0
    return box_surface((x_m - h, y_m - h, 0.0), (x_m + h, y_m + h, height_m), density, rng)


def legs_cloud(x_m: float, y_m: float, density: float, rng: np.random.Generator) -> FloatArray:
    """A standing person's legs: two cylinders 0.12 m across, 0.8 m tall, 0.25 m apart."""
    chunks = []
    for dy in (-0.125, 0.125):
        count = int(math.pi * 0.12 * 0.8 * density)
        angle = rng.uniform(-math.pi, math.pi, count)
        chunks.append(
            np.column_stack(
                (
                    x_m + 0.06 * np.cos(angle),
                    y_m + dy + 0.06 * np.sin(angle),
                    rng.uniform(0.0, 0.8, count),
                )
            )
        )
    return np.concatenate(chunks)


def noisy(cloud: FloatArray, sigma_m: float, rng: np.random.Generator) -> FloatArray:
    return cloud + rng.normal(0.0, sigma_m, cloud.shape)
