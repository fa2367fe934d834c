"""The vehicle file's forklift tables: ``[forks]`` and ``[pallets]``.

Kinouchi et al.'s automated guided forklift (AGF) steers its rear axle and carries its
forks ahead; what it is judged by is where the forks end up against a pallet's
openings, so the forks' geometry is part of the vehicle, like a scanner's mount. The
pallet guidance's distances and speeds are the vehicle owner's to set, like the
docking's: a forklift in a busy storage area moves at a walking pace.
"""

from __future__ import annotations

from typing import Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from appliance.mapping.pallets import PalletKind


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class Forks(_Model):
    """The forks in the vehicle frame (x forward from the vehicle's centre, y left)."""

    # From the vehicle's centre to the forks' heel (the carriage face, where a pallet
    # stops when it is fully on the forks), along x; the forks point forward from it.
    heel_forward_m: float = Field(1.0, ge=0.0, le=10.0)
    length_m: float = Field(1.07, gt=0.3, le=3.0)  # ISO 2331: 1070 mm, a common fork
    # Centre to centre of the two forks: fits both standard pallets' openings.
    spread_m: float = Field(0.56, gt=0.1, le=2.0)
    width_m: float = Field(0.12, gt=0.03, le=0.5)  # one fork's (ISO 2331 class II: 100-125 mm)
    # Lateral offset of the forks' centre line (a side shifter's position; 0 = centred).
    offset_y_m: float = Field(0.0, ge=-0.5, le=0.5)

    @property
    def tips_forward_m(self) -> float:
        return self.heel_forward_m + self.length_m


class SiteLandmark(_Model):
    """A reflector post of the site (a vertical cylinder): the forklift localizes on
    these (Kinouchi et al. presume a known pose; the kit gets it from the posts)."""

    name: str = Field(min_length=1, max_length=64)
    x_m: float = Field(ge=-1e5, le=1e5)
    y_m: float = Field(ge=-1e5, le=1e5)
    radius_m: float = Field(gt=0.01, le=2.0)


class SiteWall(_Model):
    """A wall or rack face the planner keeps clear of (a segment in the site frame): the
    merged map holds pallets only, so what else stands in the storage area is listed."""

    name: str = Field("wall", min_length=1, max_length=64)
    x0_m: float = Field(ge=-1e5, le=1e5)
    y0_m: float = Field(ge=-1e5, le=1e5)
    x1_m: float = Field(ge=-1e5, le=1e5)
    y1_m: float = Field(ge=-1e5, le=1e5)


class SiteColumn(_Model):
    """A column or post that is no landmark (another radius, no reflector): kept clear of."""

    name: str = Field("column", min_length=1, max_length=64)
    x_m: float = Field(ge=-1e5, le=1e5)
    y_m: float = Field(ge=-1e5, le=1e5)
    radius_m: float = Field(gt=0.0, le=10.0)


class WorkerMarker(_Model):
    """The floor marker where the worker's terminal starts its map: the worker map's
    origin in the site frame (the paper's initial T0; the merge fits the rest)."""

    x_m: float = Field(0.0, ge=-1e5, le=1e5)
    y_m: float = Field(0.0, ge=-1e5, le=1e5)
    yaw_deg: float = Field(0.0, ge=-360.0, le=360.0)


class PalletGuidanceSettings(_Model):
    """How the forklift approaches a pallet it is sent to (the `pallet` autopilot source)."""

    # The worker's map (a PLY point cloud or a JSON object list: `dbw merge`'s forms),
    # merged with the vehicle's own pallets once it stands localized; "builtin:pallets"
    # is the simulated terminal's survey of the simulated `pallets` site.
    worker_map: str = Field("", max_length=4096)
    worker_marker: WorkerMarker = WorkerMarker()
    # The merge's weight of posture against position (eq. 1's w); unset: a consumer
    # terminal's (20 mm / 1 deg)^2, as `dbw merge`.
    merge_w_m2_per_rad2: float | None = Field(None, gt=0.0, le=1e6)
    landmarks: tuple[SiteLandmark, ...] = ()
    walls: tuple[SiteWall, ...] = ()
    columns: tuple[SiteColumn, ...] = ()

    # The pallet footprints the vehicle's detections are matched against.
    kinds: tuple[PalletKind, ...] = (PalletKind.EUR, PalletKind.JIS)
    # Where the fork tips stop before the pallet's face for the final straight approach
    # to start: the re-detection happens from here (the pallet well inside both
    # scanners' fields), and the last straight is this long.
    approach_standoff_m: float = Field(1.5, ge=0.5, le=10.0)
    # How near the fork tips go: 0 = at the face (the openings), > 0 stops short.
    final_gap_m: float = Field(0.0, ge=0.0, le=1.0)
    cruise_speed_mps: float = Field(0.8, gt=0.0, le=3.0)
    final_speed_mps: float = Field(0.2, gt=0.0, le=1.0)
    # The pallet must be re-detected this near to where the map puts it, or the
    # approach is refused (a different pallet, or the worker's map is off).
    redetect_gate_m: float = Field(0.5, gt=0.0, le=3.0)
    # How fast the guidance turns the steering it wishes for: the servo must follow it
    # within safety.steer_tracking_tolerance_deg (its lag, ~0.3 s on the simulated
    # forklift, times this rate), or the tracking rule stops the vehicle. Also the rate
    # the approach plans its speed for (slower where the wheels must turn).
    steer_rate_deg_per_s: float = Field(8.0, gt=0.0, le=90.0)
    # Final-approach tolerances the vehicle must be inside before the forks go in.
    max_lateral_error_m: float = Field(0.01, gt=0.0, le=0.2)
    max_heading_error_deg: float = Field(0.3, gt=0.0, le=5.0)

    @model_validator(mode="after")
    def _speeds_are_ordered(self) -> Self:
        if self.final_speed_mps > self.cruise_speed_mps:
            raise ValueError(
                "final_speed_mps must not exceed cruise_speed_mps "
                f"(got {self.final_speed_mps} > {self.cruise_speed_mps})"
            )
        if not self.kinds:
            raise ValueError("kinds must name at least one pallet footprint")
        names = [landmark.name for landmark in self.landmarks]
        doubled = sorted({name for name in names if names.count(name) > 1})
        if doubled:
            raise ValueError(f"landmarks named twice: {', '.join(doubled)}")
        radii = {landmark.radius_m for landmark in self.landmarks}
        if len(radii) > 1:
            # The localizer's extraction tests every arc against one radius.
            raise ValueError(
                f"landmarks must all have one radius (got {', '.join(map(str, sorted(radii)))} m)"
            )
        return self


class TabletPageSettings(_Model):
    """The tablet page (`appliance/tablet_page/`): a worker guides the forklift from a
    tablet on the site's network (Kinouchi et al., Fig. 6). Off by default; it listens on
    the address given (the vehicle PC's on the site's WLAN), every request authenticated
    with a token paired by the code `dbw status` shows. Only with hold-to-move: the
    tablet's button is the panel's ENGAGE held, and nothing more."""

    enabled: bool = False
    host: str = Field("127.0.0.1", min_length=1, max_length=255)
    port: int = Field(8090, ge=0, le=65535)
    # Other names the tablet may use for the vehicle (its DNS name); any other Host
    # header is refused (a web page elsewhere resolving its name to the vehicle).
    host_names: tuple[str, ...] = ()
    # The page beats every 0.1 s while the button is held; this long without a beat and
    # the hold lapses (the mode machine's hold-to-move then stops the vehicle).
    hold_timeout_s: float = Field(0.3, ge=0.15, le=2.0)
