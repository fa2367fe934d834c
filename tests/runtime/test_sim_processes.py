"""`dbw sim` and `dbw run` in separate processes: the daemon reaches the twins as hardware."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from appliance.config import load_config


def test_daemon_in_another_process_reaches_the_simulator(tmp_path: Path) -> None:
    daemon_config = tmp_path / "via-sim.toml"
    sim = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "appliance",
            "--log-format",
            "json",
            "sim",
            "--write-config",
            str(daemon_config),
            "--pty-dir",
            str(tmp_path / "ptys"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + 30
        while not daemon_config.exists() and time.monotonic() < deadline:
            assert sim.poll() is None, sim.stdout.read() if sim.stdout else ""
            time.sleep(0.1)
        assert daemon_config.exists()
        config = load_config(daemon_config)
        assert not config.simulation.enabled
        assert config.devices.brake_serial.port.startswith(str(tmp_path))

        run = subprocess.run(
            [
                sys.executable,
                "-m",
                "appliance",
                "--log-format",
                "json",
                "run",
                "--config",
                str(daemon_config),
                "--duration-s",
                "3",
            ],
            capture_output=True,
            text=True,
            timeout=60,
            env=dict(os.environ),
            check=False,
        )
        assert run.returncode == 0, run.stderr
        events = [json.loads(x) for x in run.stdout.splitlines() if x.startswith("{")]
        beats = [e for e in events if e["event"] == "heartbeats"]
        assert beats
        links = beats[-1]["links"]
        assert links["lms111_left"].startswith("streaming")
        assert links["lms111_right"].startswith("streaming")
        for board in ("steering", "throttle", "brake", "panel"):
            assert links[f"board.{board}"].startswith("up "), links
        ages = beats[-1]["input_ages_s"]
        assert ages["scan.left"] < 0.2
        assert ages["board.brake"] < 0.2
    finally:
        sim.send_signal(signal.SIGTERM)
        try:
            sim.wait(timeout=10)
        finally:
            if sim.poll() is None:
                sim.kill()
    assert sim.returncode == 0
