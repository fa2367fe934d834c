"""Builders that turn a few parameters into the shapes of a launcher, pallets, a yard.

Each builder takes a validated spec (a frozen pydantic model: the same object a site
TOML table is validated into, so a file and a test build identical geometry) and
returns a ``Site`` fragment; fragments are merged into one site.

Dimensions: neither seed paper gives numbers for the objects, so the defaults are
plausible choices, each marked below with where it comes from.

Launcher frame (Qian et al., Fig. 4 and Fig. 7 "global coordinates fixed on the
launcher"): origin at the centre of the front board's face, +x along the launcher's
central axis pointing INTO the launcher (the heading the vehicle has when docked), +y
to the left of a vehicle facing the board. The launcher pose (x_m, y_m, yaw_deg) places
that frame in the world, so the docking target is that pose moved back by the standoff.
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from appliance.sim.site import (
    PERSON_RADIUS_M,
    WALKING_SPEED_MPS,
    Circle,
    Segment,
    Site,
    SitePallet,
)
from appliance.sim.site import Walker as _Walker
from drivers.geometry import Pose2D

Coordinate = Annotated[float, Field(ge=-1000.0, le=1000.0)]
Yaw = Annotated[float, Field(ge=-360.0, le=360.0)]
# Relative to white paper: ~0.1 black paint, ~0.9 white paint, up to ~10 for reflector foil.
Remission = Annotated[float, Field(ge=0.0, le=10.0)]


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class LauncherSpec(_Spec):
    """Qian et al.'s simplified launcher: one big front board, two small side boards,
    one cylindrical landmark on each side (Section 3.1, Fig. 4)."""

    x_m: Coordinate = 0.0
    y_m: Coordinate = 0.0
    yaw_deg: Yaw = 0.0
    # Not given in the paper ("one big front board"). 3 m: wider than the flat-bed's
    # front end, so both LMS111 at the vehicle's head see it until docking.
    front_board_width_m: float = Field(3.0, gt=0.0, le=20.0)
    # "Two small boards"; length not given. 0.8 m gives ~30 points at 10 m and 0.25°.
    side_board_length_m: float = Field(0.8, gt=0.0, le=10.0)
    # Each side board is hinged at an end of the front board and swept back from the
    # front board's line by this angle: 0° continues the front board outward, 90° is
    # perpendicular and recedes into the launcher (edge-on from the front), negative
    # angles point toward the approaching vehicle (a funnel mouth). The paper finds the
    # initial pose from "the corners between the front and the side boards", so both
    # must be visible from the approach zone ~10 m in front: 45° back is, and it stays
    # out of the way of the docking vehicle. The paper gives no angle.
    side_board_sweep_deg: float = Field(45.0, ge=-90.0, le=90.0)
    # "Cylindrical landmarks on both sides"; 0.15 m radius (a 0.3 m pipe) gives an arc
    # of ~7 points at 10 m, enough for the paper's arc fitting.
    cylinder_radius_m: float = Field(0.15, gt=0.0, le=2.0)
    # Centre distance from the central axis: beside the vehicle's path, never hit by it.
    cylinder_lateral_m: float = Field(2.5, gt=0.0, le=50.0)
    # How far in front of the board plane (toward the vehicle) the cylinders stand; in
    # front so neither the boards nor the side boards hide them during the approach.
    cylinder_ahead_m: float = Field(0.5, ge=-20.0, le=20.0)
    board_remission: Remission = 0.9  # painted for "easy perception by laser scanners"
    cylinder_remission: Remission = 0.9
    # Distance from the front board at which the vehicle's front end centre stops. The
    # paper docks until "the longitudinal distance to the launcher approaches zero".
    docking_standoff_m: float = Field(0.0, ge=0.0, le=20.0)
    name: str = "launcher"

    @property
    def pose(self) -> Pose2D:
        return Pose2D(self.x_m, self.y_m, math.radians(self.yaw_deg))


def launcher_docking_target(spec: LauncherSpec) -> Pose2D:
    """Where the vehicle's front-end centre must stop, and the heading it must have."""
    return spec.pose.compose(Pose2D(-spec.docking_standoff_m, 0.0, 0.0))


def launcher_site(spec: LauncherSpec) -> Site:
    pose = spec.pose
    half = spec.front_board_width_m / 2.0
    sweep = math.radians(spec.side_board_sweep_deg)
    back_m = spec.side_board_length_m * math.sin(sweep)  # +x: into the launcher
    out_m = spec.side_board_length_m * math.cos(sweep)  # away from the central axis

    def segment(a: tuple[float, float], b: tuple[float, float], part: str) -> Segment:
        (x0, y0), (x1, y1) = pose.apply(*a), pose.apply(*b)
        return Segment(x0, y0, x1, y1, spec.board_remission, f"{spec.name}.{part}")

    segments = (
        segment((0.0, -half), (0.0, half), "front_board"),
        segment((0.0, half), (back_m, half + out_m), "side_board_left"),
        segment((0.0, -half), (back_m, -half - out_m), "side_board_right"),
    )
    circles = tuple(
        Circle(
            *pose.apply(-spec.cylinder_ahead_m, side * spec.cylinder_lateral_m),
            spec.cylinder_radius_m,
            spec.cylinder_remission,
            f"{spec.name}.cylinder_{label}",
        )
        for side, label in ((1.0, "left"), (-1.0, "right"))
    )
    return Site(
        segments,
        circles,
        name=spec.name,
        targets=((f"{spec.name}.docking", launcher_docking_target(spec)),),
    )


class PalletAreaSpec(_Spec):
    """Kinouchi et al.'s reference objects: pallets on the floor of a temporary storage
    area, here in a grid, optionally jittered as a worker would leave them."""

    # Centre of pallet (row 0, column 0) and the area's heading; rows advance along the
    # area's x (the fork entry direction), columns along its y.
    x_m: Coordinate = 0.0
    y_m: Coordinate = 0.0
    yaw_deg: Yaw = 0.0
    rows: int = Field(2, ge=1, le=50)
    columns: int = Field(3, ge=1, le=50)
    # The paper only says "a pallet having a standardized shape". 1.1 m x 1.1 m is the
    # Japanese standard T11 pallet (JIS Z 0601), the likely one at MHI; 1.2 m x 1.0 m
    # (ISO 6780) is the other common choice. Fork pockets are ignored: the outline only.
    pallet_length_m: float = Field(1.1, gt=0.0, le=5.0)
    pallet_width_m: float = Field(1.1, gt=0.0, le=5.0)
    # What the scan plane does not show, for the worker's 3D terminal: a block pallet's
    # height (ISO 6780: 144 mm) and the cargo on it (a box of the pallet's footprint).
    pallet_height_m: float = Field(0.144, gt=0.0, le=2.0)
    cargo_height_m: float = Field(0.0, ge=0.0, le=5.0)
    gap_x_m: float = Field(1.0, ge=0.0, le=50.0)  # aisle for a fork to approach
    gap_y_m: float = Field(0.5, ge=0.0, le=50.0)
    # Random misplacement of each pallet ("placed anywhere at the site worker's
    # discretion"), drawn from `seed` so a site file always builds the same geometry.
    jitter_m: float = Field(0.0, ge=0.0, le=5.0)
    jitter_deg: float = Field(0.0, ge=0.0, le=180.0)
    seed: int = Field(0, ge=0)
    remission: Remission = 0.5  # bare wood
    name: str = "pallets"


def pallet_area_site(spec: PalletAreaSpec) -> Site:
    area = Pose2D(spec.x_m, spec.y_m, math.radians(spec.yaw_deg))
    rng = np.random.default_rng(spec.seed)
    hl, hw = spec.pallet_length_m / 2.0, spec.pallet_width_m / 2.0
    corners = ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))  # front-left, counter-clockwise
    sides = ("left", "back", "right", "front")  # side i runs from corner i to corner i+1
    segments: list[Segment] = []
    targets: list[tuple[str, Pose2D]] = []
    solids: list[SitePallet] = []
    for row in range(spec.rows):
        for column in range(spec.columns):
            dx, dy = rng.uniform(-spec.jitter_m, spec.jitter_m, size=2)
            dyaw = math.radians(float(rng.uniform(-spec.jitter_deg, spec.jitter_deg)))
            local = Pose2D(
                row * (spec.pallet_length_m + spec.gap_x_m) + float(dx),
                column * (spec.pallet_width_m + spec.gap_y_m) + float(dy),
                dyaw,
            )
            pallet = area.compose(local)
            label = f"{spec.name}.r{row}c{column}"
            world = [pallet.apply(x, y) for x, y in corners]
            for i, side in enumerate(sides):
                (x0, y0), (x1, y1) = world[i], world[(i + 1) % 4]
                segments.append(Segment(x0, y0, x1, y1, spec.remission, f"{label}.{side}"))
            targets.append((label, pallet))
            solids.append(
                SitePallet(
                    label,
                    pallet,
                    spec.pallet_length_m,
                    spec.pallet_width_m,
                    spec.pallet_height_m,
                    spec.cargo_height_m,
                )
            )
    return Site(tuple(segments), name=spec.name, targets=tuple(targets), pallets=tuple(solids))


class YardSpec(_Spec):
    """A rectangular boundary (fence, buildings) so that not every beam returns 0."""

    x_m: Coordinate = 0.0  # centre
    y_m: Coordinate = 0.0
    length_m: float = Field(40.0, gt=0.0, le=2000.0)  # extent along x
    width_m: float = Field(40.0, gt=0.0, le=2000.0)  # extent along y
    remission: Remission = 0.4  # weathered concrete
    name: str = "yard"


def yard_site(spec: YardSpec) -> Site:
    x0, x1 = spec.x_m - spec.length_m / 2.0, spec.x_m + spec.length_m / 2.0
    y0, y1 = spec.y_m - spec.width_m / 2.0, spec.y_m + spec.width_m / 2.0
    walls = (
        (x1, y0, x1, y1, "wall_east"),
        (x1, y1, x0, y1, "wall_north"),
        (x0, y1, x0, y0, "wall_west"),
        (x0, y0, x1, y0, "wall_south"),
    )
    return Site(
        tuple(Segment(a, b, c, d, spec.remission, f"{spec.name}.{w}") for a, b, c, d, w in walls),
        name=spec.name,
    )


class PostSpec(_Spec):
    """A post, bollard or lamp standard: clutter the feature extractor must reject."""

    x_m: Coordinate
    y_m: Coordinate
    radius_m: float = Field(0.1, gt=0.0, le=5.0)  # a 0.2 m steel post
    remission: Remission = 0.3
    name: str = "post"

    def circle(self) -> Circle:
        return Circle(self.x_m, self.y_m, self.radius_m, self.remission, self.name)


class WalkerSpec(_Spec):
    """A person pacing a polyline back and forth (see ``site.Walker``)."""

    waypoints_m: list[tuple[Coordinate, Coordinate]] = Field(min_length=1, max_length=100)
    speed_mps: float = Field(WALKING_SPEED_MPS, ge=0.0, le=5.0)
    radius_m: float = Field(PERSON_RADIUS_M, gt=0.0, le=2.0)
    remission: Remission = 0.3
    phase_s: float = Field(0.0, ge=0.0, le=1e6)
    name: str = "person"

    def walker(self) -> _Walker:
        return _Walker(
            tuple((float(x), float(y)) for x, y in self.waypoints_m),
            self.speed_mps,
            self.radius_m,
            self.remission,
            self.name,
            self.phase_s,
        )


class SegmentSpec(_Spec):
    """A free-standing wall or board given by its two ends."""

    x0_m: Coordinate
    y0_m: Coordinate
    x1_m: Coordinate
    y1_m: Coordinate
    remission: Remission = 0.5
    name: str = "wall"

    def segment(self) -> Segment:
        return Segment(self.x0_m, self.y0_m, self.x1_m, self.y1_m, self.remission, self.name)


def clutter_site(
    posts: tuple[PostSpec, ...] = (),
    walkers: tuple[WalkerSpec, ...] = (),
    segments: tuple[SegmentSpec, ...] = (),
) -> Site:
    return Site(
        tuple(s.segment() for s in segments),
        tuple(p.circle() for p in posts),
        tuple(w.walker() for w in walkers),
        name="clutter",
    )
