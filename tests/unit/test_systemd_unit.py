"""The shipped unit file: systemd itself must accept it, and it must say what we rely on."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[2] / "systemd" / "dbw.service"


def unit_settings() -> dict[str, list[str]]:
    settings: dict[str, list[str]] = {}
    for raw in UNIT.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", "[")):
            continue
        key, _, value = line.partition("=")
        settings.setdefault(key, []).append(value)
    return settings


def test_systemd_analyze_verify_accepts_the_unit(tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.fail("systemd-analyze is missing: `make test` installs Debian's systemd package")
    # verify checks that ExecStart exists; point it at this checkout's dbw, change nothing else.
    dbw = Path(sys.executable).with_name("dbw")
    assert dbw.exists(), dbw
    text = UNIT.read_text().replace("/opt/dbw/venv/bin/dbw", str(dbw))
    unit = tmp_path / "dbw.service"
    unit.write_text(text)
    result = subprocess.run(
        [analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 0, result.stderr
    assert "dbw.service" not in result.stderr, result.stderr  # no warnings about our unit


def test_verify_would_catch_a_broken_unit(tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    assert analyze is not None
    unit = tmp_path / "dbw.service"
    unit.write_text(UNIT.read_text().replace("Type=notify", "Type=notifyy"))
    result = subprocess.run(
        [analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60, check=False
    )
    assert "notifyy" in result.stderr  # verify exits 0 on warnings; we read stderr


def test_unit_declares_notify_watchdog_restart_and_hardening() -> None:
    settings = unit_settings()
    expected = {
        "Type": "notify",
        "Restart": "on-failure",
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "StateDirectory": "dbw",
        "User": "dbw",
    }
    for key, value in expected.items():
        assert settings.get(key) == [value], key
    watchdog_s = float(settings["WatchdogSec"][0].removesuffix("s"))
    assert 0 < watchdog_s <= 5
    assert "AF_CAN" in settings["RestrictAddressFamilies"][0]
    assert "dialout" in settings["SupplementaryGroups"][0]
    assert any("ttyUSB" in d for d in settings["DeviceAllow"])
    # The daemon needs 1 s to stop; systemd must not SIGKILL it before that.
    assert float(settings["TimeoutStopSec"][0].removesuffix("s")) >= 2


def test_unit_is_well_formed_ini() -> None:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.read_string(UNIT.read_text())
    assert {"Unit", "Service", "Install"} <= set(parser.sections())
