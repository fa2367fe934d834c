"""`dbw route record`'s choice of epochs: each once, only good ones, moved to the anchor."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.cli import route_record
from appliance.cli.route_record import EpochFilter, _keep
from appliance.localization.local_frame import LocalFrame
from appliance.routes import Route, read_route_file


def entry(t: float, east: float = 10.0, north: float = 5.0, yaw: float = 90.0, **kw: object):
    return {
        "measurement_time_s": t,
        "fix": True,
        "east_m": east,
        "north_m": north,
        "yaw_deg": yaw,
        "sigma_m": 0.03,
    } | kw


def feed() -> EpochFilter:
    # Antenna 1 m forward of the centre and 0.5 m to its left; the anchor 3 m forward.
    return EpochFilter(
        anchor_forward_m=3.0, antenna_forward_m=1.0, antenna_left_m=0.5, max_sigma_m=0.15
    )


def test_the_anchor_is_ahead_of_the_antenna_along_the_heading() -> None:
    # Heading north (90° ENU): the anchor is 2 m further north and 0.5 m to the right
    # (east) of the antenna, which sits 0.5 m left of the centre line.
    point = feed().update(entry(1.0, yaw=90.0))
    assert point == pytest.approx((10.5, 7.0, 1.0))
    point = feed().update(entry(1.0, yaw=0.0))  # heading east: right is south
    assert point == pytest.approx((12.0, 4.5, 1.0))


def test_each_epoch_once_and_the_bad_ones_counted() -> None:
    f = feed()
    assert f.update(entry(1.0)) is not None
    assert f.update(entry(1.0)) is None and f.skipped == {}  # seen again: not a skip
    assert f.update(entry(1.1, fix=False)) is None
    assert f.update(entry(1.2, sigma_m=0.4)) is None
    assert f.update(entry(1.3, yaw_deg=None)) is None
    assert f.update(None) is None
    assert f.update(entry(1.4)) is not None
    assert f.skipped == {
        "no fix": 1,
        "sigma above 0.15 m": 1,
        "no position or heading": 1,
        "no receiver or no epoch yet": 1,
    }


@given(st.dictionaries(st.sampled_from(list(entry(0.0))), st.none() | st.floats() | st.text()))
def test_any_entry_gives_a_finite_point_or_none(values: dict[str, object]) -> None:
    point = feed().update(entry(0.0) | values)
    assert point is None or all(math.isfinite(v) for v in point)


def test_record_without_a_daemon_or_with_a_bad_name_says_so(tmp_path: object) -> None:
    from click.testing import CliRunner

    from appliance.cli.main import cli

    base = ["route", "record", "--config", "husky-sim", "--dir", str(tmp_path)]
    result = CliRunner().invoke(cli, [*base, "yard", "--socket", f"{tmp_path}/none.sock"])
    assert result.exit_code == 2 and "dbw:" in result.output
    result = CliRunner().invoke(cli, [*base, "../etc/passwd", "--socket", "/dev/null"])
    assert result.exit_code == 2 and "error:" in result.output
    result = CliRunner().invoke(cli, ["route", "record", "yard", "--config", "husky-sim"])
    assert result.exit_code == 2 and "built-in" in result.output  # not into the package


def test_a_refused_recording_is_kept_without_overwriting_anything(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    frame = LocalFrame(42.4591, -71.2674, 100.0)
    drive = Route.from_enu("drive", np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]]), frame)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "drive.geojson").write_text("somebody's file")
    _keep(drive, "drive")
    assert (tmp_path / "drive.geojson").read_text() == "somebody's file"
    kept = [p for p in tmp_path.iterdir() if p.name.startswith("drive-")]
    assert len(kept) == 1 and read_route_file(kept[0]).point_count == 3
    capsys.readouterr()

    def refuse(path: object, route: object) -> None:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(route_record, "write_route_file", refuse)
    _keep(drive, "drive")  # nowhere to write: on standard output, not lost
    out = capsys.readouterr()
    assert "cannot write" in out.err and json.loads(out.out)["properties"]["name"] == "drive"
