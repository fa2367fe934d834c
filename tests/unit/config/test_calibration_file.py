"""The calibration file: every rule refuses what it should, the writer round-trips, the CLI."""

from __future__ import annotations

import json
import math
import os
import tempfile
import threading
import tomllib
from datetime import UTC, datetime
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.cli.calibration import calibration
from appliance.config.atomic import write_text_atomic
from appliance.config.calibration import (
    MIN_WHEEL_TRAVEL_RAD,
    Calibration,
    CalibrationFile,
    CounterSteerCalibration,
    GuidanceCalibration,
    SteeringCalibration,
)
from appliance.config.calibration_file import (
    BUILTIN_SIMULATED,
    CalibrationError,
    dumps_calibration,
    load_calibration,
    parse_calibration,
    read_calibration_file,
    write_calibration,
)
from appliance.guidance.pure_pursuit import LookaheadSchedule
from calibration.pot_map import MAX_POT_TO_WHEEL_COEFFS

# The example of the format's documentation, as raw TOML values, table by table.
BASE: dict[str, dict[str, str]] = {
    "": {
        "schema_version": "1",
        "vehicle_name": '"sim"',
        "created_utc": '"2026-12-01T15:00:00Z"',
        "source": '"maneuver pot_centre + pot_map on 2026-12-01"',
    },
    "steering": {
        "pot_centre_counts": "2131.0",
        "pot_to_wheel_coeffs": "[0.0055, 0.0, 1.2e-10]",
        "pot_valid_min_counts": "400",
        "pot_valid_max_counts": "3860",
        "steering_ratio": "18.0",
    },
    "counter_steer": {"k_ratio": "0.63"},
    "guidance": {"look_ahead_m": "4.0"},
}


def calfile_text(changes: dict[str, str | None] | None = None) -> str:
    """BASE with ``{"table.key": raw value}`` changes; None deletes the key (or table)."""
    tables = {table: dict(values) for table, values in BASE.items()}
    for dotted, value in (changes or {}).items():
        table, _, key = dotted.rpartition(".")
        if value is None and dotted in tables:
            del tables[dotted]
        elif value is None:
            del tables[table][key]
        else:
            tables.setdefault(table, {})[key] = value
    out = [f"{key} = {value}" for key, value in tables.pop("").items()]
    for table, values in tables.items():
        out.append(f"\n[{table}]")
        out += [f"{key} = {value}" for key, value in values.items()]
    return "\n".join(out) + "\n"


def problems_of(text: str, vehicle_name: str = "sim") -> dict[str, str]:
    with pytest.raises(CalibrationError) as caught:
        parse_calibration(text, vehicle_name, "test.toml")
    return {problem.field: problem.message for problem in caught.value.problems}


def test_the_documented_example_loads() -> None:
    model = parse_calibration(calfile_text(), "sim")
    assert model.steering.pot_to_wheel_coeffs == (0.0055, 0.0, 1.2e-10)
    assert model.created_utc == datetime(2026, 12, 1, 15, tzinfo=UTC)
    assert model.counter_steer == CounterSteerCalibration(k_ratio=0.63)
    assert model.guidance == GuidanceCalibration(look_ahead_m=4.0)


def test_optional_sections_may_be_absent_or_empty() -> None:
    text = calfile_text({"counter_steer.k_ratio": None, "guidance.look_ahead_m": None})
    model = parse_calibration(text, "sim")
    assert model.counter_steer == CounterSteerCalibration()
    assert model.guidance == GuidanceCalibration()
    without = calfile_text({"counter_steer": None, "guidance": None})
    assert "guidance" not in without
    assert parse_calibration(without, "sim").counter_steer is None
    assert parse_calibration(without, "sim").guidance is None


@pytest.mark.parametrize(
    ("changes", "field", "fragment"),
    [
        ({"steering.pot_centre_counts": "5000"}, "steering.pot_centre_counts", "got 5000"),
        ({"steering.pot_centre_counts": "-1"}, "steering.pot_centre_counts", "0.0 <= value"),
        ({"steering.pot_valid_min_counts": "-5"}, "steering.pot_valid_min_counts", "0 <= value"),
        ({"steering.pot_valid_max_counts": "4096"}, "steering.pot_valid_max_counts", "4095"),
        ({"steering.pot_valid_min_counts": "400.5"}, "steering.pot_valid_min_counts", "400.5"),
        ({"steering.steering_ratio": "1.0"}, "steering.steering_ratio", "1.0 < value"),
        ({"steering.steering_ratio": "61"}, "steering.steering_ratio", "value <= 60.0"),
        ({"steering.pot_to_wheel_coeffs": "[]"}, "steering.pot_to_wheel_coeffs", "at least 1"),
        (
            {"steering.pot_to_wheel_coeffs": "[" + ", ".join(["0.0055"] * 10) + "]"},
            "steering.pot_to_wheel_coeffs",
            f"at most {MAX_POT_TO_WHEEL_COEFFS}",
        ),
        (
            {"steering.pot_to_wheel_coeffs": "[nan, 0.0055]"},
            "steering.pot_to_wheel_coeffs[0]",
            "finite",
        ),
        (
            {"steering.pot_to_wheel_coeffs": "[0.0055, inf]"},
            "steering.pot_to_wheel_coeffs[1]",
            "finite",
        ),
        ({"counter_steer.k_ratio": "1.6"}, "counter_steer.k_ratio", "value <= 1.5"),
        ({"counter_steer.k_ratio": "-0.1"}, "counter_steer.k_ratio", "0.0 <= value"),
        ({"guidance.look_ahead_m": "0"}, "guidance.look_ahead_m", "0.0 < value"),
        ({"guidance.look_ahead_m": "51"}, "guidance.look_ahead_m", "value <= 50.0"),
        ({"vehicle_name": '""'}, "vehicle_name", "at least 1"),
        ({"source": '""'}, "source", "at least 1"),
        ({"created_utc": '"yesterday"'}, "created_utc", "yesterday"),
        ({"created_utc": '"2026-12-01T15:00:00+02:00"'}, "created_utc", "UTC"),
        ({"created_utc": '"2026-12-01T15:00:00"'}, "created_utc", "timezone"),
        ({"steering.steering_ratio": None}, "steering.steering_ratio", "required"),
        ({"source": None}, "source", "required"),
    ],
)
def test_each_field_rule_names_the_field(
    changes: dict[str, str | None], field: str, fragment: str
) -> None:
    problems = problems_of(calfile_text(changes))
    assert list(problems) == [field]
    assert fragment in problems[field]


def test_every_problem_is_reported_not_just_the_first() -> None:
    problems = problems_of(
        calfile_text({"steering.steering_ratio": "0.5", "counter_steer.k_ratio": "9"})
    )
    assert set(problems) == {"steering.steering_ratio", "counter_steer.k_ratio"}


def test_missing_steering_table_is_refused() -> None:
    text = calfile_text().split("[steering]")[0]
    assert "required" in problems_of(text)["steering"]


@pytest.mark.parametrize(
    "changes",
    [
        {"steering.pot_valid_min_counts": "2200"},  # min above centre
        {"steering.pot_valid_min_counts": "2131"},  # min at centre
        {"steering.pot_centre_counts": "3860.0"},  # centre at max
    ],
)
def test_centre_must_lie_strictly_inside_the_valid_range(changes: dict[str, str | None]) -> None:
    message = problems_of(calfile_text(changes))["steering"]
    assert "pot_centre_counts must lie strictly between" in message


def test_a_map_that_folds_inside_the_valid_range_is_refused() -> None:
    # slope 0.0055 - 3e-9 d^2 is zero at d = +-1354 counts, inside -1731..1729
    message = problems_of(calfile_text({"steering.pot_to_wheel_coeffs": "[0.0055, 0.0, -1e-9]"}))[
        "steering"
    ]
    assert "pot_to_wheel_coeffs is not strictly monotonic" in message
    assert "near 77" in message  # the fold at 2131 - 1354 = 777 counts


def test_the_same_fold_outside_the_valid_range_is_accepted() -> None:
    text = calfile_text(
        {
            "steering.pot_to_wheel_coeffs": "[0.0055, 0.0, -1e-9]",
            "steering.pot_valid_min_counts": "800",
            "steering.pot_valid_max_counts": "3460",
        }
    )
    assert parse_calibration(text, "sim").steering.pot_valid_min_counts == 800


def test_a_constant_map_is_refused() -> None:
    message = problems_of(calfile_text({"steering.pot_to_wheel_coeffs": "[0.0, 0.0]"}))["steering"]
    assert "steering-wheel angle" in message  # 0 rad at the ends: caught as implausible travel


def test_a_decreasing_map_is_accepted_and_inverted() -> None:
    text = calfile_text({"steering.pot_to_wheel_coeffs": "[-0.0055, 0.0, -1.2e-10]"})
    cal = Calibration.from_file(parse_calibration(text, "sim"))
    wheel_rad = cal.wheel_rad_from_counts(3000.0)
    assert wheel_rad is not None
    assert wheel_rad < 0.0
    low, high = cal.valid_tyre_range_rad
    assert low < 0.0 < high
    assert cal.counts_from_wheel_rad(-2.0) > cal.pot_centre_counts
    assert cal.wheel_rad_from_counts(cal.counts_from_wheel_rad(-2.0)) == pytest.approx(-2.0)


@pytest.mark.parametrize(
    ("coeffs", "fragment"),
    [
        ("[1e-5]", "0.01731 rad"),  # a coefficient per degree-ish typo: far too little travel
        ("[0.02]", "-34.62 rad"),  # far too much
    ],
)
def test_implausible_wheel_travel_is_refused(coeffs: str, fragment: str) -> None:
    message = problems_of(calfile_text({"steering.pot_to_wheel_coeffs": coeffs}))["steering"]
    assert "pot_to_wheel_coeffs gives" in message
    assert fragment in message
    assert "0.5..30.0 rad" in message


@pytest.mark.parametrize(
    ("value", "given"),
    [("2", "unsupported version 2"), ('"1"', "unsupported version '1'"), ("true", "True")],
)
def test_other_schema_versions_are_refused_alone(value: str, given: str) -> None:
    # an unknown field next to it is not reported: a newer schema may define it
    problems = problems_of(calfile_text({"schema_version": value, "steering.new_field": "1"}))
    assert list(problems) == ["schema_version"]
    assert given in problems["schema_version"]
    assert "schema_version = 1 only" in problems["schema_version"]


def test_missing_schema_version_is_refused() -> None:
    problems = problems_of(calfile_text({"schema_version": None}))
    assert problems["schema_version"].startswith("missing")


@pytest.mark.parametrize(
    ("changes", "field", "suggestion"),
    [
        (
            {"steering.pot_centre_counts": None, "steering.pot_centre_count": "2131.0"},
            "steering.pot_centre_count",
            "pot_centre_counts",
        ),
        ({"vehicle_nmae": '"sim"'}, "vehicle_nmae", "vehicle_name"),
        ({"guidance.lookahead_m": "4.0"}, "guidance.lookahead_m", "look_ahead_m"),
        ({"stearing.steering_ratio": "18.0"}, "stearing", "steering"),
    ],
)
def test_unknown_keys_get_a_did_you_mean(
    changes: dict[str, str | None], field: str, suggestion: str
) -> None:
    assert problems_of(calfile_text(changes))[field] == (
        f"unknown field; did you mean {suggestion!r}?"
    )


def test_a_file_for_another_vehicle_is_refused() -> None:
    message = problems_of(calfile_text(), vehicle_name="husky")["vehicle_name"]
    assert "'sim'" in message
    assert "'husky'" in message


def test_missing_file_says_how_to_get_one(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError) as caught:
        load_calibration(tmp_path / "nope.toml", "sim")
    rendered = caught.value.render()
    assert rendered.startswith(f"{tmp_path / 'nope.toml'}: 1 problem(s)")
    assert "not found: run the calibration maneuvers" in rendered
    assert "paths.calibration_file" in rendered


def test_toml_syntax_error_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "cal.toml"
    path.write_text(calfile_text().replace("steering_ratio = 18.0", "steering_ratio = = 18"))
    with pytest.raises(CalibrationError) as caught:
        load_calibration(path, "sim")
    assert "not valid TOML" in caught.value.render()
    assert "line 11" in caught.value.render()


@pytest.mark.parametrize("make_bad", ["binary", "directory"])
def test_unreadable_file_is_a_calibration_error(tmp_path: Path, make_bad: str) -> None:
    path = tmp_path / "cal.toml"
    if make_bad == "binary":
        path.write_bytes(b"\xff\xfe\x00garbage")
    else:
        path.mkdir()
    with pytest.raises(CalibrationError, match="cannot read the file"):
        load_calibration(path, "sim")


def test_render_has_one_line_per_problem() -> None:
    with pytest.raises(CalibrationError) as caught:
        parse_calibration(calfile_text({"steering.steering_ratio": "0"}), "sim", "cal.toml")
    assert caught.value.render() == (
        "cal.toml: 1 problem(s)\n"
        "  - steering.steering_ratio: Input should be greater than 1 (got 0); "
        "allowed: 1.0 < value <= 60.0"
    )


def test_builtin_simulated_only_with_the_simulation() -> None:
    cal = load_calibration(BUILTIN_SIMULATED, "bench", simulation_enabled=True)
    assert cal.vehicle_name == "bench"
    assert "simulated vehicle's true mapping" in cal.source
    with pytest.raises(CalibrationError, match="simulated vehicle's calibration on a real vehicle"):
        load_calibration(BUILTIN_SIMULATED, "bench")


# --- the runtime view ---------------------------------------------------------------------


@pytest.fixture
def example() -> Calibration:
    return Calibration.from_file(parse_calibration(calfile_text(), "sim"))


def test_wheel_angle_is_the_polynomial_of_the_offset(example: Calibration) -> None:
    d = 1000.0
    assert example.wheel_rad_from_counts(2131.0) == 0.0
    assert example.wheel_rad_from_counts(2131.0 + d) == pytest.approx(0.0055 * d + 1.2e-10 * d**3)
    assert example.tyre_rad_from_counts(2131.0 + d) == pytest.approx(
        (0.0055 * d + 1.2e-10 * d**3) / 18.0
    )
    assert example.counter_steer_k_ratio == 0.63
    # An older file's constant look-ahead: the schedule at that length at every speed.
    assert example.guidance_schedule == LookaheadSchedule(4.0, 0.0, 4.0, 4.0)


@pytest.mark.parametrize("counts", [399.0, 399.999, 3860.001, 4095.0, -1.0, math.nan, math.inf])
def test_readings_outside_the_valid_range_mean_nothing(example: Calibration, counts: float) -> None:
    assert example.wheel_rad_from_counts(counts) is None
    assert example.tyre_rad_from_counts(counts) is None


def test_the_valid_range_is_inclusive(example: Calibration) -> None:
    low, high = example.valid_wheel_range_rad
    assert example.wheel_rad_from_counts(400) == low
    assert example.wheel_rad_from_counts(3860) == high
    tyre_low, tyre_high = example.valid_tyre_range_rad
    assert (tyre_low, tyre_high) == (low / 18.0, high / 18.0)
    assert math.degrees(tyre_low) == pytest.approx(-32.285, abs=1e-3)


@given(st.floats(400.0, 3860.0))
def test_counts_from_wheel_rad_inverts_the_map(counts: float) -> None:
    cal = Calibration.from_file(parse_calibration(calfile_text(), "sim"))
    wheel_rad = cal.wheel_rad_from_counts(counts)
    assert wheel_rad is not None
    assert cal.counts_from_wheel_rad(wheel_rad) == pytest.approx(counts, abs=1e-6)


@pytest.mark.parametrize("beyond", [-1e-3, 1e-3])
def test_counts_from_wheel_rad_refuses_angles_outside_the_range(
    example: Calibration, beyond: float
) -> None:
    low, high = example.valid_wheel_range_rad
    with pytest.raises(ValueError, match="outside the calibrated range"):
        example.counts_from_wheel_rad((low if beyond < 0 else high) + beyond)


# --- writing ------------------------------------------------------------------------------

names = st.text(st.characters(codec="utf-8"), min_size=1, max_size=64)


@st.composite
def calibration_files(draw: st.DrawFn) -> CalibrationFile:
    centre = draw(st.floats(500.0, 3595.0))
    low = draw(st.integers(max(0, math.ceil(centre) - 2000), math.ceil(centre) - 300))
    high = draw(st.integers(math.floor(centre) + 300, min(4095, math.floor(centre) + 2000)))
    near, span = sorted((centre - low, high - centre))
    # The wheel travel at the far end is the drawn one, 3.5..25 rad; at the near end it is
    # near / span of it, within 2 % (the higher terms below). Drawing it at least 5 % above
    # MIN_WHEEL_TRAVEL_RAD * span / near keeps the near end valid by construction.
    least_travel = max(3.5, MIN_WHEEL_TRAVEL_RAD * 1.05 * span / near)
    linear = draw(st.sampled_from([1.0, -1.0])) * draw(st.floats(least_travel, 25.0)) / span
    count = draw(st.integers(1, MAX_POT_TO_WHEEL_COEFFS))
    # small higher terms keep the slope within 10 % of the linear one (monotonic) and the
    # travel within 2 % of the linear one (sum of 0.01 / (power + 1))
    higher = [
        draw(st.floats(-0.01, 0.01)) / (power + 1) * linear / span**power
        for power in range(1, count)
    ]
    return CalibrationFile(
        vehicle_name=draw(names),
        created_utc=draw(st.datetimes(timezones=st.just(UTC))),
        source=draw(st.text(st.characters(codec="utf-8"), min_size=1)),
        steering=SteeringCalibration(
            pot_centre_counts=centre,
            pot_to_wheel_coeffs=(linear, *higher),
            pot_valid_min_counts=low,
            pot_valid_max_counts=high,
            steering_ratio=draw(st.floats(1.0, 60.0, exclude_min=True)),
        ),
        counter_steer=draw(
            st.none() | st.builds(CounterSteerCalibration, k_ratio=st.none() | st.floats(0.0, 1.5))
        ),
        guidance=draw(
            st.none()
            | st.builds(
                GuidanceCalibration,
                look_ahead_m=st.none() | st.floats(0.0, 50.0, exclude_min=True),
            )
        ),
    )


@settings(max_examples=200, deadline=None)
@given(model=calibration_files())
def test_write_then_load_is_exact(model: CalibrationFile) -> None:
    with tempfile.TemporaryDirectory() as directory:  # a fresh one per example
        path = Path(directory) / "cal.toml"
        write_calibration(path, model)
        loaded = read_calibration_file(path, model.vehicle_name)
    assert loaded == model
    assert loaded.created_utc.tzinfo is UTC
    assert dumps_calibration(loaded) == dumps_calibration(model)  # every float bit for bit
    assert Calibration.from_file(loaded) == Calibration.from_file(model)


def test_written_text_is_plain_toml(tmp_path: Path) -> None:
    model = parse_calibration(calfile_text(), "sim")
    path = tmp_path / "deep" / "er" / "cal.toml"  # parents are created
    write_calibration(path, model)
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    assert data["steering"]["pot_to_wheel_coeffs"] == [0.0055, 0.0, 1.2e-10]
    assert data["created_utc"] == "2026-12-01T15:00:00Z"
    assert data["counter_steer"] == {"k_ratio": 0.63}
    assert os.stat(path).st_mode & 0o777 == 0o644


def test_tricky_strings_survive(tmp_path: Path) -> None:
    source = 'quote " backslash \\ tab \t newline \n nul \x00 del \x7f c1 \x85 ü 🚜 """ \\u0041'
    model = parse_calibration(calfile_text(), "sim").model_copy(update={"source": source})
    write_calibration(tmp_path / "cal.toml", model)
    assert read_calibration_file(tmp_path / "cal.toml", "sim").source == source


def _old_and_new(tmp_path: Path) -> tuple[Path, str, CalibrationFile]:
    path = tmp_path / "cal.toml"
    old = calfile_text()
    path.write_text(old, encoding="utf-8")
    new = parse_calibration(calfile_text({"steering.steering_ratio": "20.0"}), "sim")
    return path, old, new


def test_a_failed_replace_leaves_the_old_file_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path, old, new = _old_and_new(tmp_path)

    def refuse(*_: object) -> None:
        raise OSError("simulated power cut during rename")

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(OSError, match="power cut"):
        write_calibration(path, new)
    assert path.read_text(encoding="utf-8") == old
    assert os.listdir(tmp_path) == ["cal.toml"]  # no temp file left behind


def test_a_failed_fsync_leaves_the_old_file_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path, old, new = _old_and_new(tmp_path)

    def refuse(_: int) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", refuse)
    with pytest.raises(OSError, match="disk full"):
        write_calibration(path, new)
    assert path.read_text(encoding="utf-8") == old
    assert os.listdir(tmp_path) == ["cal.toml"]


def test_an_unwritable_model_touches_nothing(tmp_path: Path) -> None:
    path, old, new = _old_and_new(tmp_path)
    with pytest.raises(ValueError, match="lone surrogate"):
        write_calibration(path, new.model_copy(update={"source": "bad \udc80"}))
    assert path.read_text(encoding="utf-8") == old
    assert os.listdir(tmp_path) == ["cal.toml"]


def test_a_reader_polling_for_the_file_sees_it_whole_or_not_at_all(tmp_path: Path) -> None:
    """The race of `dbw sim --write-config`: the other side loads the file once it exists."""
    path = tmp_path / "via-sim.toml"
    versions = [("a" * 1_000_000) + "\n", ("b" * 2_000_000) + "\n"]
    seen: set[int] = set()
    torn: list[int] = []
    done = threading.Event()

    def read() -> None:
        while not done.is_set():
            try:
                text = path.read_text(encoding="utf-8")
            except FileNotFoundError:
                continue
            seen.add(len(text))
            if text not in versions:
                torn.append(len(text))

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for turn in range(20):
            write_text_atomic(path, versions[turn % 2])
    finally:
        done.set()
        reader.join()
    assert not torn, f"a reader saw partial files of {sorted(set(torn))[:5]} characters"
    assert seen <= {len(v) for v in versions}
    assert os.listdir(tmp_path) == ["via-sim.toml"]
    assert os.stat(path).st_mode & 0o777 == 0o644


def test_write_text_atomic_of_unencodable_text_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "via-sim.toml"
    path.write_text("old = 1\n", encoding="utf-8")
    with pytest.raises(UnicodeEncodeError):
        write_text_atomic(path, "new = 1\n" * 10_000 + "\udc80")
    assert path.read_text(encoding="utf-8") == "old = 1\n"
    assert os.listdir(tmp_path) == ["via-sim.toml"]


# --- the CLI ------------------------------------------------------------------------------


@pytest.fixture
def good_file(tmp_path: Path) -> Path:
    path = tmp_path / "cal.toml"
    path.write_text(calfile_text(), encoding="utf-8")
    return path


def invoke(*args: str | Path) -> tuple[int, str, str]:
    result = CliRunner().invoke(calibration, [str(arg) for arg in args])
    return result.exit_code, result.stdout, result.stderr


def test_cli_check_ok(good_file: Path) -> None:
    code, out, err = invoke("check", good_file)
    assert (code, err) == (0, "")
    assert out == (
        f"{good_file}: OK (vehicle 'sim', pot centre 2131.0 counts, tyre range -32.3..32.2 deg)\n"
    )


def test_cli_check_bad_file_exits_2_with_the_problems(tmp_path: Path) -> None:
    path = tmp_path / "cal.toml"
    path.write_text(calfile_text({"steering.steering_ratio": "99"}), encoding="utf-8")
    code, out, err = invoke("check", path)
    assert (code, out) == (2, "")
    assert err.startswith(f"{path}: 1 problem(s)\n  - steering.steering_ratio: ")


def test_cli_check_against_another_vehicle(good_file: Path) -> None:
    code, _, err = invoke("check", good_file, "--config", "husky")
    assert code == 2
    assert "vehicle_name: this file calibrates vehicle 'sim'" in err


def test_cli_check_bad_config_exits_2(good_file: Path, tmp_path: Path) -> None:
    code, _, err = invoke("check", good_file, "--config", tmp_path / "missing.toml")
    assert code == 2
    assert "no such file" in err


def test_cli_check_builtin_simulated(good_file: Path) -> None:
    code, out, _ = invoke("check", BUILTIN_SIMULATED)
    assert code == 0
    assert out.startswith("builtin:simulated: OK (vehicle 'sim', pot centre 2131.0 counts")
    code, out, err = invoke("check", BUILTIN_SIMULATED, "--config", "flatbed")
    assert (code, out) == (2, "")
    assert "a simulated vehicle's calibration on a real vehicle" in err


def test_cli_show_prints_loadable_toml(good_file: Path) -> None:
    code, out, _ = invoke("show", good_file)
    assert code == 0
    assert out.startswith(f"# {good_file}: vehicle 'sim', pot centre 2131.0 counts")
    assert parse_calibration(out, "sim") == parse_calibration(calfile_text(), "sim")


def test_cli_show_json(good_file: Path) -> None:
    code, out, _ = invoke("show", good_file, "--json")
    assert code == 0
    data = json.loads(out)
    assert data["file"] == str(good_file)
    assert data["calibration"]["steering"]["pot_to_wheel_coeffs"] == [0.0055, 0.0, 1.2e-10]
    assert data["calibration"]["created_utc"] == "2026-12-01T15:00:00Z"
    assert data["valid_tyre_range_deg"][0] == pytest.approx(-32.285, abs=1e-3)


def test_cli_show_defaults_to_the_configs_calibration_file(tmp_path: Path) -> None:
    cal = tmp_path / "bench-cal.toml"
    cal.write_text(calfile_text({"vehicle_name": '"bench"'}), encoding="utf-8")
    config = tmp_path / "bench.toml"
    config.write_text(
        f'name = "bench"\n[simulation]\nenabled = true\n[paths]\ncalibration_file = "{cal}"\n'
    )
    code, out, _ = invoke("show", "--config", config)
    assert code == 0
    assert out.startswith(f"# {cal}: vehicle 'bench'")
    code, _, err = invoke("show", "--config", "husky")  # its default path does not exist
    assert code == 2
    assert "not found" in err


def test_cli_write_simulated_then_check(tmp_path: Path) -> None:
    out_path = tmp_path / "var" / "cal.toml"
    code, out, err = invoke("write-simulated", out_path)
    assert (code, err) == (0, "")
    assert out.startswith(f"wrote {out_path} (vehicle 'sim', pot centre 2131.0 counts")
    code, out, _ = invoke("check", out_path)
    assert code == 0
    assert out.endswith("tyre range -30.2..30.2 deg)\n")
    assert "simulated" in read_calibration_file(out_path, "sim").source


def test_cli_write_simulated_warns_for_a_vehicle_without_simulation(tmp_path: Path) -> None:
    code, _, err = invoke("write-simulated", tmp_path / "cal.toml", "--config", "husky")
    assert code == 0
    assert "warning: vehicle 'husky' has simulation.enabled = false" in err
    assert read_calibration_file(tmp_path / "cal.toml", "husky").vehicle_name == "husky"
