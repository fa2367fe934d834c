"""Config: the shipped profiles load, and bad files are explained field by field."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from appliance.config import BUILTIN_PROFILES, ConfigError, VehicleConfig, load_config, parse_config
from appliance.config.models import VehicleKind
from drivers.pc104.endpoint import CanInterface


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_builtin_profiles_load(name: str) -> None:
    config = load_config(name)
    assert config.name == name


def test_default_is_the_simulated_vehicle() -> None:
    config = load_config(None)
    assert config.simulation.enabled
    assert config.devices.can.interface is CanInterface.VIRTUAL


def test_seed_vehicles_talk_to_real_hardware() -> None:
    husky = load_config("husky")
    flatbed = load_config("flatbed")
    assert husky.kind is VehicleKind.FOUR_WHEEL_COUNTER_STEER
    assert husky.geometry.counter_steer_ratio_k == pytest.approx(0.63)
    assert husky.limits.max_speed_mps == pytest.approx(4.47)  # 10 mph
    assert flatbed.kind is VehicleKind.FLATBED
    assert flatbed.devices.can.interface is CanInterface.SOCKETCAN
    # The Husky has no PC104 to talk to: speed by its own throttle and brake, position by GNSS.
    assert husky.speed_path == "pedals"
    assert husky.devices.gnss is not None and husky.devices.gnss.port.startswith("/dev/")
    for config in (husky, flatbed):
        assert not config.simulation.enabled
        assert config.devices.steering_serial.port.startswith("/dev/")


def problems_of(text: str) -> dict[str, str]:
    with pytest.raises(ConfigError) as caught:
        parse_config(text, "test.toml")
    return {p.field: p.message for p in caught.value.problems}


def test_every_problem_is_reported_with_field_and_allowed_range() -> None:
    problems = problems_of(
        """
        [limits]
        max_speed_mps = 35
        [devices.can]
        interface = "udp"
        [rates]
        control_hz = 500
        """
    )
    assert set(problems) == {"limits.max_speed_mps", "devices.can.interface", "rates.control_hz"}
    assert "got 35" in problems["limits.max_speed_mps"]
    assert "0.0 < value <= 20.0" in problems["limits.max_speed_mps"]
    assert "'socketcan', 'slcan', 'virtual'" in problems["devices.can.interface"]
    assert "10.0 <= value <= 200.0" in problems["rates.control_hz"]


def test_misspelled_field_is_named_with_a_suggestion() -> None:
    problems = problems_of("[limits]\nmax_sped_mps = 3\n")
    assert "did you mean 'max_speed_mps'" in problems["limits.max_sped_mps"]


def test_cross_field_rules() -> None:
    problems = problems_of(
        "[simulation]\nenabled = true\n[limits]\nthrottle_min_pct = 50\nthrottle_max_pct = 40\n"
    )
    assert any("throttle_min_pct must be below throttle_max_pct" in m for m in problems.values())


def test_simulated_boards_need_the_simulation() -> None:
    problems = problems_of('name = "x"\n')
    assert any("sim://steering" in m and "simulation.enabled" in m for m in problems.values())


def test_two_scanners_at_one_address_and_port_are_refused() -> None:
    problems = problems_of("[simulation]\nenabled = true\n[devices.lms111_right]\nport = 2111\n")
    assert any(
        "lms111_left and lms111_right are both at 127.0.0.1:2111" in m for m in problems.values()
    )
    # Two real scanners, each at its own address, both listen on 2111.
    load_config("flatbed")


def test_toml_syntax_error_is_one_clear_problem() -> None:
    problems = problems_of("[limits\nmax_speed_mps = 3\n")
    assert len(problems) == 1
    assert "not valid TOML" in next(iter(problems.values()))


def test_missing_file() -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_config("/nonexistent/vehicle.toml")


@settings(max_examples=200, deadline=None)
@given(
    st.dictionaries(
        st.text(max_size=8),
        st.one_of(st.integers(), st.text(max_size=5), st.floats(allow_nan=True)),
        max_size=5,
    )
)
def test_any_table_either_loads_or_raises_config_error(table: dict[str, object]) -> None:
    lines = "\n".join(f"{k!r} = {v!r}" for k, v in table.items())
    text = f"[simulation]\nenabled = true\n[limits]\n{lines}"
    outcome: VehicleConfig | ConfigError
    try:
        outcome = parse_config(text)
    except ConfigError as exc:
        outcome = exc
    if isinstance(outcome, ConfigError):
        assert outcome.problems
    else:
        assert isinstance(outcome, VehicleConfig)


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "appliance", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_cli_config_check_bad_file_exits_2_without_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[limits]\nmax_speed_mps = -1\nwheelbase = 3\n")
    result = run_cli("config", "check", str(bad))
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "limits.max_speed_mps" in result.stderr
    assert "limits.wheelbase: unknown field" in result.stderr


def test_cli_config_check_good_file(tmp_path: Path) -> None:
    good = tmp_path / "good.toml"
    good.write_text('name = "bench"\n[simulation]\nenabled = true\n')
    result = run_cli("config", "check", str(good))
    assert result.returncode == 0, result.stderr
    assert "OK" in result.stdout


def test_cli_config_show_roundtrips(tmp_path: Path) -> None:
    result = run_cli("config", "show", "husky")
    assert result.returncode == 0, result.stderr
    shown = tmp_path / "shown.toml"
    shown.write_text(result.stdout)
    assert load_config(shown) == load_config("husky")


def test_cli_version() -> None:
    from appliance import __version__

    result = run_cli("--version")
    assert result.returncode == 0
    assert __version__ in result.stdout


def test_lms111_mode_the_device_does_not_have_is_refused() -> None:
    problems = problems_of(
        "[simulation]\nenabled = true\n"
        "[devices.lms111_left]\nscan_frequency_hz = 50\nangular_resolution_deg = 0.25\n"
    )
    assert any("50 Hz with 0.25 deg" in m for m in problems.values())


def test_a_simulated_linkage_past_the_steering_limit_is_refused() -> None:
    """At 8 % the simulated tyre would reach 32.4 deg at the wheel's lock, past the Husky's
    32 deg limit where the simulated vehicle clamps it: the configured linkage would not
    be the one a calibration sees."""
    config = load_config("husky-sim")
    steering = config.simulation.steering.model_copy(update={"linkage_cubic": 0.08})
    data = config.model_copy(
        update={"simulation": config.simulation.model_copy(update={"steering": steering})}
    ).model_dump()
    with pytest.raises(ValidationError, match="linkage_cubic"):
        VehicleConfig.model_validate(data)
    data["simulation"]["steering"]["linkage_cubic"] = 0.06
    assert VehicleConfig.model_validate(data).simulation.steering.linkage_cubic == 0.06
