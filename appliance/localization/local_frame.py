"""A route's and a fix's local east-north frame: geodetic to metres around a fixed origin.

The tracker works in metres on a plane (Stanley et al. convert the route to a local frame
at their own slow rate), so every geodetic position goes through one `LocalFrame` around
the origin the vehicle file configures. pymap3d does the geodesy (WGS84, through ECEF to
east-north-up), so no flat-earth shortcut creeps in: at a kilometre from the origin a
plain degrees-to-metres scaling is already off by decimetres, more than the tracker's
whole error budget.

Pure: no I/O, floats in and floats out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pymap3d


@dataclass(frozen=True)
class LocalFrame:
    """East-north-up metres around ``(origin_lat_deg, origin_lon_deg, origin_alt_m)``
    on WGS84; the origin must be a real place (refused otherwise, at construction)."""

    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.origin_lat_deg) and abs(self.origin_lat_deg) <= 90.0):
            raise ValueError(f"origin latitude must be within ±90°, got {self.origin_lat_deg}")
        if not (math.isfinite(self.origin_lon_deg) and abs(self.origin_lon_deg) <= 180.0):
            raise ValueError(f"origin longitude must be within ±180°, got {self.origin_lon_deg}")
        if not math.isfinite(self.origin_alt_m):
            raise ValueError(f"origin altitude must be finite, got {self.origin_alt_m}")

    def to_local(
        self, lat_deg: float, lon_deg: float, alt_m: float = 0.0
    ) -> tuple[float, float, float]:
        """(east_m, north_m, up_m) of a geodetic position."""
        east, north, up = pymap3d.geodetic2enu(
            lat_deg, lon_deg, alt_m, self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m
        )
        return float(east), float(north), float(up)

    def to_geodetic(
        self, east_m: float, north_m: float, up_m: float = 0.0
    ) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_m) of a local position: `to_local`'s inverse, for
        writing a recorded route back out as GeoJSON."""
        lat, lon, alt = pymap3d.enu2geodetic(
            east_m, north_m, up_m, self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m
        )
        return float(lat), float(lon), float(alt)
