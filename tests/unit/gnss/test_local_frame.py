"""The local east-north frame against the geodesy written out here (WGS84 to ECEF, then
the rotation to east-north-up at the origin), and its inverse against itself."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.localization.local_frame import LocalFrame

A_M = 6378137.0  # WGS84
F = 1.0 / 298.257223563
E2 = F * (2.0 - F)


def _ecef(lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n = A_M / math.sqrt(1.0 - E2 * math.sin(lat) ** 2)
    return (
        (n + alt_m) * math.cos(lat) * math.cos(lon),
        (n + alt_m) * math.cos(lat) * math.sin(lon),
        (n * (1.0 - E2) + alt_m) * math.sin(lat),
    )


def _enu(point: tuple[float, float, float], origin: tuple[float, float, float]) -> list[float]:
    (x, y, z), (x0, y0, z0) = _ecef(*point), _ecef(*origin)
    dx, dy, dz = x - x0, y - y0, z - z0
    lat, lon = math.radians(origin[0]), math.radians(origin[1])
    east = -math.sin(lon) * dx + math.cos(lon) * dy
    north = (
        -math.sin(lat) * math.cos(lon) * dx
        - math.sin(lat) * math.sin(lon) * dy
        + math.cos(lat) * dz
    )
    up = (
        math.cos(lat) * math.cos(lon) * dx + math.cos(lat) * math.sin(lon) * dy + math.sin(lat) * dz
    )
    return [east, north, up]


ORIGINS = st.tuples(st.floats(-80.0, 80.0), st.floats(-179.0, 179.0), st.floats(-100.0, 3000.0))
OFFSETS = st.tuples(st.floats(-0.02, 0.02), st.floats(-0.02, 0.02), st.floats(-50.0, 50.0))


@given(ORIGINS, OFFSETS)
def test_local_coordinates_match_the_geodesy_written_out(
    origin: tuple[float, float, float], offset: tuple[float, float, float]
) -> None:
    """Within about 2 km of the origin, to a tenth of a millimetre."""
    point = (origin[0] + offset[0], origin[1] + offset[1], origin[2] + offset[2])
    got = LocalFrame(*origin).to_local(*point)
    assert got == pytest.approx(_enu(point, origin), abs=1e-4)


@given(ORIGINS, st.floats(-5000.0, 5000.0), st.floats(-5000.0, 5000.0), st.floats(-20.0, 20.0))
def test_to_geodetic_undoes_to_local(
    origin: tuple[float, float, float], east: float, north: float, up: float
) -> None:
    frame = LocalFrame(*origin)
    back = frame.to_local(*frame.to_geodetic(east, north, up))
    assert back == pytest.approx((east, north, up), abs=1e-6)


def test_an_arc_second_north_is_the_meridians_arc() -> None:
    """One arc-second of latitude at 52° N is the meridian's radius of curvature there
    times the angle (30.908 m), not the 30.887 m a sphere of the mean radius gives."""
    frame = LocalFrame(52.0, 9.0)
    east, north, up = frame.to_local(52.0 + 1.0 / 3600.0, 9.0)
    lat = math.radians(52.0)
    meridian_m = A_M * (1.0 - E2) / (1.0 - E2 * math.sin(lat) ** 2) ** 1.5
    assert abs(east) < 1e-9
    assert north == pytest.approx(meridian_m * math.radians(1.0 / 3600.0), abs=1e-5)
    assert abs(north - 6371008.8 * math.radians(1.0 / 3600.0)) > 0.01
    assert up == pytest.approx(-(north**2) / (2 * 6.37e6), abs=1e-4)  # the earth curves away


@pytest.mark.parametrize(
    "origin", [(91.0, 0.0, 0.0), (0.0, 181.0, 0.0), (math.nan, 0.0, 0.0), (0.0, 0.0, math.inf)]
)
def test_an_origin_that_is_not_a_place_is_refused(origin: tuple[float, float, float]) -> None:
    with pytest.raises(ValueError, match="origin"):
        LocalFrame(*origin)
