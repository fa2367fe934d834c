"""`dbw localize --left FILE --right FILE` on recordings of a slow simulated approach.

Both scanners are recorded together (the right one half a period after the left, as the
twins stagger them) while the flat-bed creeps towards the launcher at 0.2 m/s, a little
off its axis; the replayed localizer's last pose must be the vehicle's true one to a few
centimetres, in the launcher's frame wherever the site puts the launcher.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from appliance.cli.localize import localize
from appliance.sim.scanner_errors import ScannerErrors
from appliance.sim.site_file import load_site
from drivers.geometry import Pose2D
from tests.runtime.recordings import (
    FLATBED_MOUNTS,
    FRONT_END_M,
    PNG_SIGNATURE,
    SERIAL_NUMBERS,
    dbw,
    header_only,
    record,
)

# Files and faster-than-real-time runs, no daemon on the clock: run with the unit tests,
# on every core (see tests/conftest.py).
pytestmark = pytest.mark.cpu_bound

SCANS = 30  # per scanner: 1.2 s at 25 Hz
SPEED_MPS = 0.2
START_GAP_M = 8.0
LATERAL_M = 0.08
HEADING_RAD = math.radians(0.4)
START_S = 1.0
STAGGER_S = 0.02


def centre_in_launcher(t_s: float) -> Pose2D:
    gap_m = START_GAP_M - SPEED_MPS * (t_s - START_S)
    return Pose2D(-(gap_m + FRONT_END_M), LATERAL_M, HEADING_RAD)


def make_pair(
    folder: Path, site_file: Path | None = None, launcher: Pose2D | None = None
) -> dict[str, Path]:

    site = load_site(site_file) if site_file is not None else None
    in_site: Callable[[float], Pose2D] = centre_in_launcher
    if launcher is not None:
        in_site = lambda t_s: launcher.compose(centre_in_launcher(t_s))  # noqa: E731
    files = {}
    for index, name in enumerate(("left", "right")):
        files[name] = folder / f"{name}.lms"
        record(
            files[name], FLATBED_MOUNTS[name], in_site, ScannerErrors(), scans=SCANS,
            start_s=START_S + index * STAGGER_S, serial_number=SERIAL_NUMBERS[name],
            noise_seed=index, site=site,
        )  # fmt: skip
    return files


@pytest.fixture(scope="module")
def approach(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return make_pair(tmp_path_factory.mktemp("approach"))


def invoke(*args: str | Path) -> tuple[int, str, str]:
    result = CliRunner().invoke(localize, [str(arg) for arg in args])
    return result.exit_code, result.stdout, result.stderr


def pair_args(files: dict[str, Path]) -> list[str | Path]:
    return ["--left", files["left"], "--right", files["right"], "--config", "flatbed"]


def last_scan_s() -> float:
    return START_S + STAGGER_S + (SCANS - 1) / 25.0


def assert_close_to_truth(centre: dict[str, float]) -> None:
    truth = centre_in_launcher(last_scan_s())
    assert abs(centre["x_m"] - truth.x_m) < 0.03, centre
    assert abs(centre["y_m"] - truth.y_m) < 0.03, centre
    assert abs(centre["heading_deg"] - math.degrees(truth.yaw_rad)) < 0.3, centre


def test_the_track_ends_on_the_true_pose(approach: dict[str, Path]) -> None:
    code, out, err = invoke(*pair_args(approach), "--json")
    assert code == 0, err
    lines = [json.loads(line) for line in out.splitlines()]
    track, summary = lines[:-1], lines[-1]
    assert len(track) == 2 * SCANS
    assert all(point["kind"] == "estimate" for point in track)
    assert {point["status"] for point in track} <= {"ok", "degraded", "lost"}
    assert track[0]["status"] == "lost"  # one scanner seen: no pose yet
    assert track[0]["reason"] == "waiting for every scanner"
    assert track[0]["centre"] is None
    times = [point["t_s"] for point in track]
    assert times == sorted(times)
    assert [p["scanner"] for p in track[:4]] == ["left", "right", "left", "right"]
    final = track[-1]
    assert final["status"] == "ok"
    assert final["quality"] > 50
    assert_close_to_truth(final["centre"])
    assert final["centre"]["sigma_y_m"] < 0.05
    assert set(final["nis"]) == {"board", "cylinder"}
    assert final["accepted"]["cylinder"] > SCANS
    assert summary["kind"] == "summary"
    assert summary["frame"] == "launcher"
    assert summary["scans"] == 2 * SCANS
    assert summary["scans_by_scanner"] == {"left": SCANS, "right": SCANS}
    assert summary["first_pose_after_s"] == pytest.approx(STAGGER_S)
    assert summary["time_s"]["ok"] > 0.9 * summary["duration_s"]
    assert sum(summary["time_s"].values()) == pytest.approx(summary["duration_s"])
    assert summary["final"] == final
    assert summary["recordings"]["left"]["scans"] == SCANS


def test_text_track_and_summary(approach: dict[str, Path]) -> None:
    code, out, err = invoke(*pair_args(approach))
    assert code == 0, err
    lines = out.splitlines()
    assert "no pose: waiting for every scanner" in lines[0]
    assert " ok " in lines[5]
    assert "heading" in lines[5]
    assert any(line.startswith("first pose at t=") for line in lines)
    assert lines[-1].startswith("final: ok")


def test_png_draws_the_track(approach: dict[str, Path], tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    png = tmp_path / "track.png"
    code, _, err = invoke(*pair_args(approach), "--png", png)
    assert code == 0, err
    data = png.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    assert len(data) > 20_000


def test_poses_are_in_the_launcher_frame_of_the_site_given(tmp_path: Path) -> None:
    site_file = tmp_path / "moved.toml"
    site_file.write_text(
        "[launcher]\nx_m = 4.0\ny_m = -2.0\nyaw_deg = 20.0\n"
        "front_board_width_m = 2.8\ncylinder_lateral_m = 2.2\n"
    )
    launcher = Pose2D(4.0, -2.0, math.radians(20.0))
    files = make_pair(tmp_path, site_file, launcher)
    code, out, err = invoke(*pair_args(files), "--site", site_file, "--json")
    assert code == 0, err
    summary = json.loads(out.splitlines()[-1])
    assert summary["launcher_in_site"] == {"x_m": 4.0, "y_m": -2.0, "yaw_deg": 20.0}
    assert summary["final"]["status"] == "ok"
    assert_close_to_truth(summary["final"]["centre"])
    # Against the built-in launcher (its cylinders 0.3 m further out) the pose is wrong,
    # and cylinders are rejected: the site's dimensions are the ones used.
    code, out, err = invoke(*pair_args(files), "--json")
    assert code == 0, err
    final = json.loads(out.splitlines()[-1])["final"]
    assert abs(final["centre"]["y_m"] - LATERAL_M) > 0.1
    assert final["rejected"]["cylinder"] > 0


def test_a_cut_off_recording_is_used_up_to_the_cut(
    approach: dict[str, Path], tmp_path: Path
) -> None:
    cut = tmp_path / "cut.lms"
    cut.write_bytes(approach["right"].read_bytes()[:-100])
    code, out, err = invoke(
        "--left", approach["left"], "--right", cut, "--config", "flatbed", "--json"
    )
    assert code == 1
    summary = json.loads(out.splitlines()[-1])
    assert summary["scans_by_scanner"] == {"left": SCANS, "right": SCANS - 1}
    assert summary["recordings"]["right"]["truncated"]
    assert err.startswith("warning:")


def test_bad_input_exits_2_with_one_line(approach: dict[str, Path], tmp_path: Path) -> None:
    junk = tmp_path / "junk.lms"
    junk.write_bytes(b"not a recording at all\n")
    empty = tmp_path / "empty.lms"
    header_only(empty)
    later = tmp_path / "later.lms"
    record(
        later, FLATBED_MOUNTS["right"], centre_in_launcher, ScannerErrors(), scans=2,
        start_s=100.0, serial_number=SERIAL_NUMBERS["right"],
    )  # fmt: skip
    no_launcher = tmp_path / "yard.toml"
    no_launcher.write_text("[yard]\nlength_m = 30.0\nwidth_m = 30.0\n")
    bad_site = tmp_path / "bad.toml"
    bad_site.write_text("[launcher]\ncylinder_radius_mm = 0.2\n")
    left, right = str(approach["left"]), str(approach["right"])
    cases = {
        "both front scanners": ["--left", left],
        "not an LMS111 recording": ["--left", left, "--right", str(junk)],
        "cannot read": ["--left", str(tmp_path / "missing.lms"), "--right", right],
        "no scans": ["--left", left, "--right", str(empty)],
        "same scanner": ["--left", left, "--right", left],
        "do not overlap": ["--left", left, "--right", str(later)],
        "no [launcher]": ["--left", left, "--right", right, "--site", str(no_launcher)],
        "cylinder_radius_mm": ["--left", left, "--right", right, "--site", str(bad_site)],
        "none.toml": [
            "--left", left, "--right", right, "--calibration", str(tmp_path / "none.toml")
        ],
    }  # fmt: skip
    for expected, args in cases.items():
        code, out, err = invoke(*args, "--config", "flatbed")
        assert code == 2, (args, out, err)
        assert expected in err, err
        assert len(err.strip().splitlines()) == 1, err


def test_the_installed_command_reports_corrupt_input(
    approach: dict[str, Path], tmp_path: Path
) -> None:
    junk = tmp_path / "junk.lms"
    junk.write_bytes(b"LMS111REC 1 {}\n")  # a header without host, port, dialect
    code, _, err = dbw("localize", "--left", str(approach["left"]), "--right", str(junk))
    assert code == 2
    assert "unreadable header" in err
    assert "Traceback" not in err
