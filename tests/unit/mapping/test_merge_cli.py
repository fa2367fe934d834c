"""`dbw merge` and `dbw sim survey` as a user runs them: files in, a report out."""

from __future__ import annotations

import json
import math
from pathlib import Path

from click.testing import CliRunner

from appliance.cli.main import cli
from appliance.mapping.object_file import parse_object_map
from drivers.geometry import Pose2D

# The worker map's origin in the vehicle map (what the floor marker only estimates).
TRUE_WORKER_IN_VEHICLE = Pose2D(2.0, -1.0, math.radians(30.0))
LAYOUT = [  # vehicle-map poses: (x, y, yaw_deg, kind)
    (4.0, -4.0, 0.0, "1100x1100"),
    (4.0, -2.5, 0.0, "1100x1100"),
    (4.0, 0.5, 0.0, "1100x1100"),
    (9.0, 1.0, 90.0, "1100x1100"),
    (7.5, 4.0, 90.0, "1200x800"),
    (6.2, -3.5, 0.0, "1200x800"),  # the worker's alone: behind the front row
]


def _entry(name: str, pose: Pose2D, kind: str) -> dict[str, object]:
    return {
        "name": name,
        "kind": kind,
        "x_m": pose.x_m,
        "y_m": pose.y_m,
        "yaw_deg": math.degrees(pose.yaw_rad),
        "sigma_xy_m": 0.02,
        "sigma_yaw_deg": 1.0,
    }


def _maps(tmp_path: Path, vehicle_count: int = 5) -> tuple[Path, Path]:
    c, s = math.cos(TRUE_WORKER_IN_VEHICLE.yaw_rad), math.sin(TRUE_WORKER_IN_VEHICLE.yaw_rad)
    vehicle, worker = [], []
    for index, (x, y, yaw_deg, kind) in enumerate(LAYOUT):
        pose = Pose2D(x, y, math.radians(yaw_deg))
        if index < vehicle_count:
            vehicle.append(_entry(f"v{index}", pose, kind))
        dx, dy = x - TRUE_WORKER_IN_VEHICLE.x_m, y - TRUE_WORKER_IN_VEHICLE.y_m
        in_worker = Pose2D(
            c * dx + s * dy, -s * dx + c * dy, pose.yaw_rad - TRUE_WORKER_IN_VEHICLE.yaw_rad
        )
        worker.append(_entry(f"w{index}", in_worker, kind))
    vehicle_file, worker_file = tmp_path / "vehicle.json", tmp_path / "worker.json"
    vehicle_file.write_text(json.dumps({"frame": "vehicle", "objects": vehicle}))
    worker_file.write_text(json.dumps({"frame": "worker", "objects": worker}))
    return vehicle_file, worker_file


def test_merge_finds_the_transform_adds_the_unseen_pallet_and_writes_the_map(
    tmp_path: Path,
) -> None:
    vehicle_file, worker_file = _maps(tmp_path)
    out, png = tmp_path / "merged.json", tmp_path / "merged.png"
    result = CliRunner().invoke(
        cli,
        ["merge", str(vehicle_file), str(worker_file), "--t0", "2.05,-0.95,31",
         "--out", str(out), "--png", str(png), "--json"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    inverse = report["worker_in_vehicle"]
    assert math.isclose(inverse["x_m"], 2.0, abs_tol=1e-6)
    assert math.isclose(inverse["y_m"], -1.0, abs_tol=1e-6)
    assert math.isclose(inverse["theta_deg"], 30.0, abs_tol=1e-6)
    assert len(report["pairs"]) == 5 and report["added"] == 1
    added = [p for p in report["merged"] if p["from"] == "worker"]
    assert math.isclose(added[0]["x_m"], 6.2, abs_tol=1e-5)
    assert math.isclose(added[0]["y_m"], -3.5, abs_tol=1e-5)
    assert added[0]["reference_area"]["radius_m"] > 0.72  # at least the half diagonal
    merged = parse_object_map(out.read_bytes())
    assert len(merged) == 6
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_merge_refuses_a_map_with_too_few_common_pallets(tmp_path: Path) -> None:
    vehicle_file, worker_file = _maps(tmp_path, vehicle_count=2)
    result = CliRunner().invoke(
        cli, ["merge", str(vehicle_file), str(worker_file), "--t0", "2,-1,30"]
    )
    assert result.exit_code == 1
    assert "not merged" in result.output


def test_merge_names_what_is_wrong_with_its_input(tmp_path: Path) -> None:
    vehicle_file, worker_file = _maps(tmp_path)
    broken = tmp_path / "broken.json"
    broken.write_text('{"objects": [{"name": "a", "kind": "1200x800", "x_m": 1}]}')
    result = CliRunner().invoke(cli, ["merge", str(vehicle_file), str(broken), "--t0", "0,0,0"])
    assert result.exit_code == 2
    assert "objects[0].y_m" in result.output
    result = CliRunner().invoke(
        cli, ["merge", str(vehicle_file), str(tmp_path / "none.ply"), "--t0", "0,0,0"]
    )
    assert result.exit_code == 2 and "cannot read" in result.output
    cloud = tmp_path / "cut.ply"
    cloud.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n")
    result = CliRunner().invoke(cli, ["merge", str(vehicle_file), str(cloud), "--t0", "0,0,0"])
    assert result.exit_code == 2 and "cut.ply" in result.output
    result = CliRunner().invoke(cli, ["merge", str(vehicle_file), str(worker_file), "--t0", "1,2"])
    assert result.exit_code == 2 and "X,Y,THETA_DEG" in result.output


def test_sim_survey_writes_an_object_list_merge_reads(tmp_path: Path) -> None:
    out = tmp_path / "worker.json"
    result = CliRunner().invoke(
        cli, ["sim", "survey", "--objects", "--seed", "3", "--out", str(out), "--json"]
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["count"] == 13 and report["t0"] == "0,0,0"
    assert len(parse_object_map(out.read_bytes())) == 13
