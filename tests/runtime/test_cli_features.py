"""`dbw features FILE` on recordings of the flat-bed standing 6-10 m before the launcher.

The front board is the line x = gap + 6 m ahead of the flat-bed's centre (its front end
is 6 m ahead of it), facing it (α ≈ 0), 3 m long; the cylinders stand 0.5 m in front of
the board, 2.5 m either side of the axis. Everything is in the vehicle frame.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from appliance.cli.features import features
from appliance.sim.scanner_errors import ScannerErrors
from tests.runtime.recordings import (
    FLATBED,
    FLATBED_MOUNTS,
    FRONT_END_M,
    PNG_SIGNATURE,
    SERIAL_NUMBERS,
    centre_at_gap,
    dbw,
    header_only,
    record,
)

# Files and faster-than-real-time runs, no daemon on the clock: run with the unit tests,
# on every core (see tests/conftest.py).
pytestmark = pytest.mark.cpu_bound

SCANS = 3
GAPS_M = {"left": 6.0, "right": 10.0}


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("features")
    files = {}
    for index, (name, gap_m) in enumerate(GAPS_M.items()):
        files[name] = folder / f"{name}.lms"
        record(
            files[name],
            FLATBED_MOUNTS[name],
            lambda _t, gap_m=gap_m: centre_at_gap(gap_m),
            ScannerErrors(),
            scans=SCANS,
            serial_number=SERIAL_NUMBERS[name],
            noise_seed=index,
        )
    return files


def invoke(*args: str | Path) -> tuple[int, str, str]:
    result = CliRunner().invoke(features, [str(arg) for arg in args])
    return result.exit_code, result.stdout, result.stderr


@pytest.mark.parametrize("scanner", ["left", "right"])
def test_the_front_board_and_both_cylinders_are_found(
    recordings: dict[str, Path], scanner: str
) -> None:
    code, out, err = invoke(
        recordings[scanner], "--config", "flatbed", "--scanner", scanner, "--json"
    )
    assert code == 0, err
    lines = [json.loads(line) for line in out.splitlines()]
    scans, summary = lines[:-1], lines[-1]
    assert [s["kind"] for s in scans] == ["scan"] * SCANS
    assert summary["kind"] == "summary"
    assert summary["scans"] == summary["scans_shown"] == SCANS
    assert summary["frame"] == "vehicle"
    assert summary["mount"]["x_m"] == pytest.approx(5.8)
    board_x = GAPS_M[scanner] + FRONT_END_M
    for scan in scans:
        boards = [
            line
            for line in scan["lines"]
            if abs(line["alpha_deg"]) < 1.0 and abs(line["r_m"] - board_x) < 0.05
        ]
        assert len(boards) == 1, scan["lines"]
        board = boards[0]
        assert board["length_m"] == pytest.approx(3.0, abs=0.25)
        assert sorted(y for _, y in (board["start_xy_m"], board["end_xy_m"])) == pytest.approx(
            [-1.5, 1.5], abs=0.15
        )
        assert board["sigma_r_m"] < 0.01
        assert isinstance(board["start_occluded"], bool)
        for side in (1.0, -1.0):
            near = [
                c
                for c in scan["cylinders"]
                if abs(c["cx_m"] - (board_x - 0.5)) < 0.05 and abs(c["cy_m"] - side * 2.5) < 0.05
            ]
            assert len(near) == 1, scan["cylinders"]
            assert near[0]["n_points"] >= 3
            assert near[0]["sigma_x_m"] < 0.05
        assert all(start < stop for start, stop in scan["segments"])
        assert all(isinstance(count, int) for count in scan["rejections"].values())


def test_text_summary_and_one_scan(recordings: dict[str, Path]) -> None:
    code, out, err = invoke(
        recordings["left"], "--config", "flatbed", "--scanner", "left", "--scan", "1"
    )
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("scan 1 t=")
    assert sum(line.strip().startswith("cylinder") for line in lines) >= 2
    assert any(line.strip().startswith("line") for line in lines)
    assert lines[-1].startswith(f"1 of {SCANS} scans of the left scanner (flatbed")


def test_the_scanner_is_known_by_the_endpoint_it_was_recorded_from(tmp_path: Path) -> None:
    device = FLATBED.devices.lms111_right
    path = tmp_path / "right.lms"
    record(
        path, FLATBED_MOUNTS["right"], lambda _t: centre_at_gap(8.0), ScannerErrors(), scans=1,
        endpoint=(device.host, device.port),
    )  # fmt: skip
    code, out, err = invoke(path, "--config", "flatbed", "--json")
    assert code == 0, err
    assert json.loads(out.splitlines()[-1])["scanner"] == "right"


def test_png_draws_a_scan(recordings: dict[str, Path], tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    png = tmp_path / "scan.png"
    code, out, err = invoke(
        recordings["right"], "--config", "flatbed", "--scanner", "right",
        "--scan", "2", "--png", png, "--json",
    )  # fmt: skip
    assert code == 0, err
    data = png.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    assert len(data) > 20_000
    assert json.loads(out.splitlines()[-1])["png"] == str(png)


def test_a_cut_off_recording_is_used_up_to_the_cut(
    recordings: dict[str, Path], tmp_path: Path
) -> None:
    cut = tmp_path / "cut.lms"
    cut.write_bytes(recordings["left"].read_bytes()[:-100])
    code, out, err = invoke(cut, "--config", "flatbed", "--scanner", "left", "--json")
    assert code == 1
    assert json.loads(out.splitlines()[-1])["scans"] == SCANS - 1
    assert err.startswith("warning:")
    assert "truncated" in err


def test_bad_input_exits_2_with_one_line(recordings: dict[str, Path], tmp_path: Path) -> None:
    junk = tmp_path / "junk.lms"
    junk.write_bytes(b"not a recording at all\n")
    empty = tmp_path / "empty.lms"
    header_only(empty)
    left = str(recordings["left"])
    cases = {
        "not an LMS111 recording": [str(junk), "--config", "flatbed", "--scanner", "left"],
        "cannot read": [str(tmp_path / "missing.lms"), "--config", "flatbed", "--scanner", "left"],
        "no scans": [str(empty), "--config", "flatbed", "--scanner", "left"],
        "--scanner left|right": [left, "--config", "flatbed"],  # 127.0.0.1 is neither's
        "no scan 7": [left, "--config", "flatbed", "--scanner", "left", "--scan", "7"],
        "none.toml": [
            left, "--config", "flatbed", "--scanner", "left", "--calibration",
            str(tmp_path / "none.toml"),
        ],
    }  # fmt: skip
    for expected, args in cases.items():
        code, out, err = invoke(*args)
        assert code == 2, (args, out, err)
        assert expected in err, err
        assert len(err.strip().splitlines()) == 1, err
    code, _, err = invoke(left, "--config", "no-such-vehicle", "--scanner", "left")
    assert code == 2
    assert "no-such-vehicle" in err


def test_the_installed_command_reports_corrupt_input(tmp_path: Path) -> None:
    junk = tmp_path / "junk.lms"
    junk.write_bytes(b"LMS111REC 1 {not json\n")
    code, _, err = dbw("features", str(junk), "--scanner", "left")
    assert code == 2
    assert "unreadable header" in err
    assert "Traceback" not in err
