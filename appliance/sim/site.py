"""The simulated site as plain geometry: segments, circles, and people walking about.

The scanners see a 2D slice of the world at their scan height, so a site is a set of
line segments (boards, walls, pallet sides) and circles (cylinder landmarks, posts, a
person's legs-and-torso blob). Everything is frozen: a site is data, and what moves is
a pure function of time (``Walker.position_at(t_s)``), so a simulation can be replayed,
stepped faster than real time, or sampled at any instant by a test.

``Site.shapes_at(t_s)`` hands the ray caster flat arrays; the static part is built once
and cached because two scanners at 50 Hz ask for it a hundred times a second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from drivers.geometry import Pose2D

WALKING_SPEED_MPS = 1.2  # a brisk adult walk; what a person crossing a site does
PERSON_RADIUS_M = 0.25  # shoulder-width blob at scanner height (~0.5 m across)


@dataclass(frozen=True)
class Segment:
    """A flat surface seen edge-on by the scan plane (a board, a wall, a pallet side)."""

    x0_m: float
    y0_m: float
    x1_m: float
    y1_m: float
    # Diffuse reflectivity relative to white paper (SICK's "remission": ~0.1 black,
    # ~0.9 white, > 1 retro-reflective foil). The twin maps it to the RSSI channel.
    remission: float = 0.5
    name: str = ""

    @property
    def length_m(self) -> float:
        return math.hypot(self.x1_m - self.x0_m, self.y1_m - self.y0_m)


@dataclass(frozen=True)
class Circle:
    """A vertical cylinder cut by the scan plane (a landmark, a post, a person)."""

    cx_m: float
    cy_m: float
    radius_m: float
    remission: float = 0.5
    name: str = ""

    def __post_init__(self) -> None:
        if not self.radius_m > 0.0:
            raise ValueError(f"circle {self.name!r}: radius_m must be > 0, got {self.radius_m}")


@dataclass(frozen=True)
class Walker:
    """A person walking a polyline back and forth at constant speed, forever.

    Ping-pong rather than a loop so a two-point path is a person pacing between two
    spots, the commonest case; ``phase_s`` staggers several walkers on one path.
    """

    waypoints_m: tuple[tuple[float, float], ...]
    speed_mps: float = WALKING_SPEED_MPS
    radius_m: float = PERSON_RADIUS_M
    remission: float = 0.3  # clothing: dark to mid-grey
    name: str = "person"
    phase_s: float = 0.0

    def __post_init__(self) -> None:
        if not self.waypoints_m:
            raise ValueError(f"walker {self.name!r}: needs at least one waypoint")
        if not self.speed_mps >= 0.0:
            raise ValueError(f"walker {self.name!r}: speed_mps must be >= 0")
        if not self.radius_m > 0.0:
            raise ValueError(f"walker {self.name!r}: radius_m must be > 0")

    @cached_property
    def _cumulative_m(self) -> tuple[float, ...]:
        lengths = [0.0]
        for (x0, y0), (x1, y1) in zip(self.waypoints_m, self.waypoints_m[1:], strict=False):
            lengths.append(lengths[-1] + math.hypot(x1 - x0, y1 - y0))
        return tuple(lengths)

    @property
    def path_length_m(self) -> float:
        return self._cumulative_m[-1]

    def position_at(self, t_s: float) -> tuple[float, float]:
        """Where the walker is at time ``t_s`` (metres, world frame)."""
        length = self.path_length_m
        if length <= 0.0 or self.speed_mps == 0.0:
            return self.waypoints_m[0]
        travelled = (self.speed_mps * (t_s + self.phase_s)) % (2.0 * length)
        along = travelled if travelled <= length else 2.0 * length - travelled
        cumulative = self._cumulative_m
        for leg in range(1, len(cumulative)):
            if along <= cumulative[leg] or leg == len(cumulative) - 1:
                leg_length = cumulative[leg] - cumulative[leg - 1]
                fraction = 0.0 if leg_length <= 0.0 else (along - cumulative[leg - 1]) / leg_length
                fraction = min(max(fraction, 0.0), 1.0)
                (x0, y0), (x1, y1) = self.waypoints_m[leg - 1], self.waypoints_m[leg]
                return x0 + fraction * (x1 - x0), y0 + fraction * (y1 - y0)
        return self.waypoints_m[-1]  # unreachable: the loop always returns

    def circle_at(self, t_s: float) -> Circle:
        x_m, y_m = self.position_at(t_s)
        return Circle(x_m, y_m, self.radius_m, self.remission, self.name)


class ShapeArrays(NamedTuple):
    """A site frozen at one instant, in the array form the ray caster takes."""

    segments: NDArray[np.float64]  # (N, 4): x0, y0, x1, y1
    segment_remission: NDArray[np.float64]  # (N,)
    circles: NDArray[np.float64]  # (M, 3): cx, cy, radius
    circle_remission: NDArray[np.float64]  # (M,)
    names: tuple[str, ...]  # N segment names, then M circle names: what hit_index points at


@dataclass(frozen=True)
class SitePallet:
    """A pallet as a solid, for what sees more than the scan plane (the worker's 3D
    terminal): its footprint's centre and length direction, its size, and the cargo
    standing on it (a box of the footprint's size; 0 for an empty pallet)."""

    name: str
    pose: Pose2D
    length_m: float
    width_m: float
    height_m: float = 0.144  # ISO 6780 block pallets: 22 mm deck, 100 mm blocks, 22 mm base
    cargo_height_m: float = 0.0


@dataclass(frozen=True)
class Site:
    """Everything a simulated scanner can see, plus named target poses for the tests.

    ``targets`` holds poses worth knowing exactly in a simulation (the launcher docking
    pose, each pallet's centre) as (name, pose) pairs, so the truth the estimator is
    scored against comes from the same builder that placed the shapes.
    """

    segments: tuple[Segment, ...] = ()
    circles: tuple[Circle, ...] = ()
    movers: tuple[Walker, ...] = ()
    name: str = ""
    targets: tuple[tuple[str, Pose2D], ...] = field(default=())
    pallets: tuple[SitePallet, ...] = field(default=())

    def target(self, name: str) -> Pose2D:
        for target_name, pose in self.targets:
            if target_name == name:
                return pose
        known = ", ".join(n for n, _ in self.targets) or "none"
        raise KeyError(f"site {self.name!r} has no target {name!r} (targets: {known})")

    def shape(self, name: str) -> Segment | Circle:
        """A static shape by name, for tests and tools (the first one of that name)."""
        shapes: tuple[Segment | Circle, ...] = (*self.segments, *self.circles)
        for shape in shapes:
            if shape.name == name:
                return shape
        raise KeyError(f"site {self.name!r} has no shape {name!r}")

    @cached_property
    def _static(self) -> ShapeArrays:
        segments = np.array(
            [(s.x0_m, s.y0_m, s.x1_m, s.y1_m) for s in self.segments], dtype=np.float64
        ).reshape(-1, 4)
        circles = np.array(
            [(c.cx_m, c.cy_m, c.radius_m) for c in self.circles], dtype=np.float64
        ).reshape(-1, 3)
        return ShapeArrays(
            segments,
            np.array([s.remission for s in self.segments], dtype=np.float64),
            circles,
            np.array([c.remission for c in self.circles], dtype=np.float64),
            tuple(s.name for s in self.segments) + tuple(c.name for c in self.circles),
        )

    def static_shapes(self) -> ShapeArrays:
        """The shapes that never move (the same object on every call)."""
        return self._static

    def shapes_at(self, t_s: float) -> ShapeArrays:
        """Static shapes plus every walker where it is at ``t_s``."""
        static = self._static
        if not self.movers:
            return static
        moving = [m.circle_at(t_s) for m in self.movers]
        return ShapeArrays(
            static.segments,
            static.segment_remission,
            np.concatenate(
                [static.circles, np.array([(c.cx_m, c.cy_m, c.radius_m) for c in moving])]
            ),
            np.concatenate([static.circle_remission, np.array([c.remission for c in moving])]),
            static.names + tuple(c.name for c in moving),
        )

    def merged(self, other: Site, name: str | None = None) -> Site:
        """Both sites' shapes in one; used to assemble a site from builders' parts."""
        return Site(
            self.segments + other.segments,
            self.circles + other.circles,
            self.movers + other.movers,
            self.name if name is None else name,
            self.targets + other.targets,
            self.pallets + other.pallets,
        )
