"""The PC's health: probes' parsers, the clock watch, the safety rule, and the core's use.

Parsers against any text (a number, or ProbeError, never another exception); the rule
against each threshold on both sides and a monitor that stopped reporting; the core: a
full disk while engaged hands everything back (ERROR, throttle 0, brake on, steering
released), and a vehicle whose inputs do not carry the monitor is not judged by it.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.core.core import SYSTEM_HEALTH_INPUT
from appliance.modes import Mode
from drivers.actuators.messages import SteeringMode
from drivers.system.probes import (
    ClockWatch,
    ProbeError,
    SystemHealth,
    hottest_zone_c,
    parse_loadavg,
    parse_meminfo,
    parse_millidegrees,
)
from safety.system_health import SystemHealthParams, system_faults
from tests.unit.core.test_core import engaged

PARAMS = SystemHealthParams(
    max_age_s=5.0, disk_stop_free_mb=256.0, temperature_max_c=95.0, memory_min_available_mb=128.0
)


def health(**changes: float | None) -> SystemHealth:
    base = SystemHealth(
        measured_s=0.0,
        load_1m=0.5,
        cpu_count=2,
        memory_available_mb=4000.0,
        memory_total_mb=8000.0,
        disk_free_mb=50_000.0,
        disk_total_mb=100_000.0,
        temperature_c=55.0,
        wall_clock_jump_s=0.0,
        probe_duration_s=0.001,
    )
    return replace(base, **changes)  # type: ignore[arg-type]


# ---- parsers ---------------------------------------------------------------------------


def test_parsers_read_what_linux_writes() -> None:
    assert parse_loadavg("0.52 0.58 0.59 1/467 12345\n") == 0.52
    meminfo = "MemTotal:       16303932 kB\nMemFree:  1 kB\nMemAvailable:    8151966 kB\n"
    available, total = parse_meminfo(meminfo)
    assert available == pytest.approx(8151966 * 1024 / 1e6)
    assert total == pytest.approx(16303932 * 1024 / 1e6)
    assert parse_millidegrees("47500\n") == 47.5


@pytest.mark.parametrize(
    ("parse", "text"),
    [
        (parse_loadavg, ""),
        (parse_loadavg, "nan 1 2"),
        (parse_loadavg, "-1 0 0"),
        (parse_meminfo, "MemTotal: 10 kB\n"),
        (parse_meminfo, "MemTotal: 10 MB\nMemAvailable: 5 kB\n"),
        (parse_millidegrees, "hot"),
        (parse_millidegrees, "999999"),
    ],
)
def test_parsers_refuse_what_is_not_so(parse: object, text: str) -> None:
    assert callable(parse)
    with pytest.raises(ProbeError):
        parse(text)


@given(st.text(max_size=200))
def test_parsers_give_a_number_or_a_probe_error(text: str) -> None:
    for parse in (parse_loadavg, parse_meminfo, parse_millidegrees):
        try:
            value = parse(text)
        except ProbeError:
            continue
        numbers = value if isinstance(value, tuple) else (value,)
        assert all(math.isfinite(v) for v in numbers)


def test_the_hottest_readable_zone_counts_and_unreadable_ones_do_not(tmp_path: Path) -> None:
    for name, text in (
        ("thermal_zone0", "41000"),
        ("thermal_zone1", "63500"),
        ("thermal_zone2", "x"),
    ):
        (tmp_path / name).mkdir()
        (tmp_path / name / "temp").write_text(text)
    assert hottest_zone_c(tmp_path) == 63.5
    assert hottest_zone_c(tmp_path / "none") is None


def test_clock_watch_reports_a_wall_clock_step_not_time_passing() -> None:
    watch = ClockWatch()
    assert watch.update(100.0, 1_000.0) == 0.0
    assert watch.update(101.0, 1_001.0) == pytest.approx(0.0)
    assert watch.update(102.0, 1_032.0) == pytest.approx(30.0)  # set forward 30 s
    assert watch.update(103.0, 1_030.0) == pytest.approx(-3.0)  # and back 3 s


# ---- the rule --------------------------------------------------------------------------


def test_a_fit_pc_has_no_fault() -> None:
    assert system_faults(PARAMS, 0.5, 50_000.0, 55.0, 4000.0) == {}
    assert system_faults(PARAMS, 0.5, 50_000.0, None, 4000.0) == {}  # no sensor: no verdict


@pytest.mark.parametrize(
    ("disk_mb", "temp_c", "memory_mb", "fault"),
    [
        (255.9, 55.0, 4000.0, "system:disk_full"),
        (50_000.0, 95.1, 4000.0, "system:overheated"),
        (50_000.0, 55.0, 127.0, "system:memory_low"),
        (math.nan, 55.0, 4000.0, "system:disk_full"),  # a reading that is not a number
        (50_000.0, math.nan, 4000.0, "system:overheated"),
    ],
)
def test_each_limit_is_a_fault_on_its_far_side(
    disk_mb: float, temp_c: float, memory_mb: float, fault: str
) -> None:
    faults = system_faults(PARAMS, 0.5, disk_mb, temp_c, memory_mb)
    assert set(faults) == {fault}
    assert system_faults(PARAMS, 0.5, 256.0, 95.0, 128.0) == {}  # the limits themselves pass


@pytest.mark.parametrize("age_s", [5.01, 60.0, math.inf, math.nan])
def test_a_monitor_that_stopped_reporting_is_a_fault(age_s: float) -> None:
    assert set(system_faults(PARAMS, age_s, 50_000.0, 55.0, 4000.0)) == {"stale:system.health"}


# ---- in the core -----------------------------------------------------------------------


def test_a_full_disk_while_engaged_hands_everything_back() -> None:
    core, vehicle, _ = engaged()
    vehicle.advance(0.01)
    inputs = vehicle.inputs(dict(core.staleness.age_limits_s))
    ages = {**inputs.ages_s, SYSTEM_HEALTH_INPUT: 0.3}
    out = core.step(replace(inputs, ages_s=ages, system=health(disk_free_mb=100.0)), vehicle.now_s)
    assert out.mode is Mode.ERROR
    assert "system:disk_full" in {f.reason for f in core.state.faults} | {
        r.key for r in core.faults.active_faults.values()
    }
    assert not out.throttle.enable or out.throttle.position_pct == 0.0
    assert out.brake.enable
    assert out.steering.mode is SteeringMode.RELEASE


def test_a_silent_monitor_while_engaged_is_a_fault_and_none_is_not_judged() -> None:
    core, vehicle, _ = engaged()
    vehicle.advance(0.01)
    inputs = vehicle.inputs(dict(core.staleness.age_limits_s))
    assert core.step(inputs, vehicle.now_s).mode is Mode.ENGAGED  # not monitored: not judged
    vehicle.advance(0.01)
    inputs = vehicle.inputs(dict(core.staleness.age_limits_s))
    ages = {**inputs.ages_s, SYSTEM_HEALTH_INPUT: math.inf}
    out = core.step(replace(inputs, ages_s=ages), vehicle.now_s)
    assert out.mode is Mode.ERROR
