"""The Husky's speed path, `dbw run` and `dbw sim` in separate processes, as on the vehicle.

The Husky has no PC104 and no CAN: its speed is ours to hold on the throttle and brake
boards, measured by the GNSS/INS. So this HIL test's wire is serial, not vcan: the
simulated Husky (`husky-sim`) publishes its four actuator boards and its GNSS/INS receiver
on pseudo-terminals, and the daemon (simulation disabled, as on the vehicle) opens them
by the paths `dbw sim --write-config` gives it. It runs with the HIL suite (user-mode
Linux in CI, one CPU shared by the two processes and this test), which is the point: the
pedals speed loop across a process boundary on a loaded machine. The operator engages,
drives up to speed on the pedal, locks it with +, lets go; the throttle board then holds
the speed inside the configured throttle limits; a brake tap hands it back.
"""

from __future__ import annotations

import contextlib
import statistics
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from appliance.config import load_config
from appliance.config.loader import to_toml
from tests.hil.test_daemon_vcan import dbw, stop_all, wait_for
from tests.hil.test_dock_vcan import (
    STALL_RECOVERIES,
    Operator,
    ask,
    explained,
    one_cpu_allowances,
    slowly,
    start_daemon,
    status,
)
from tests.runtime.inline import free_port

LOCK_MPS = 2.0  # the operator drives up to this, then presses +
HOLD_S = 12.0

pytestmark = [pytest.mark.vcan, pytest.mark.timeout(420.0)]


def husky_config(tmp_path: Path) -> Path:
    data = load_config("husky-sim").model_dump(mode="json")
    data["devices"]["lms111_left"]["port"] = free_port()
    data["devices"]["lms111_right"]["port"] = free_port()
    one_cpu_allowances(data)
    # The fix's age limit too: a stall of that CPU delays the receiver's epochs as it
    # delays every frame (the limit's own tests are tests/unit/core/test_route_core.py
    # and tests/runtime/test_daemon_route.py).
    data["positioning"]["max_fix_age_s"] = 1.0
    data["paths"]["control_socket"] = str(tmp_path / "control.sock")
    data["rates"]["status_report_hz"] = 2.0
    path = tmp_path / "husky.toml"
    path.write_text(to_toml(data) + "\n")
    return path


def observe(bench: Path) -> dict[str, Any]:
    return dict(ask(bench, {"op": "observe"})["state"])


def test_the_husky_holds_speed_on_its_throttle_board_across_processes(tmp_path: Path) -> None:
    sim_log, daemon_log = tmp_path / "sim.log", tmp_path / "daemon.log"
    daemon_config, bench, control = (
        tmp_path / "daemon.toml",
        tmp_path / "bench.sock",
        tmp_path / "control.sock",
    )
    throttle_max_pct = load_config("husky-sim").limits.throttle_max_pct
    procs: list[subprocess.Popen[str]] = []
    try:
        with sim_log.open("w") as out:
            sim = dbw(
                "sim", "--config", str(husky_config(tmp_path)), "--write-config",
                str(daemon_config), "--pty-dir", str(tmp_path / "ptys"), "--bench-socket",
                str(bench), stdout=out,
            )  # fmt: skip
        procs.append(sim)
        wait_for(daemon_config.exists, 60, "dbw sim to write its config", sim_log, (sim,))
        written = load_config(str(daemon_config))
        assert not written.simulation.enabled and written.speed_path == "pedals"
        assert written.devices.gnss is not None and written.devices.gnss.port.startswith("/")
        daemon = start_daemon(daemon_config, daemon_log)
        procs.append(daemon)
        alive = (sim, daemon)
        operator = Operator(bench)

        def engageable() -> bool:
            document = status(control)
            operator.clear_stall(document, engaged=False)
            return document.get("mode") == "ready" and not document.get("engage_blockers")

        held: list[dict[str, Any]] = []
        for attempt in range(STALL_RECOVERIES + 1):
            explained(slowly(engageable), 120, "the Husky engageable", daemon_log, alive)
            doc = status(control)
            assert "pc104" not in doc.get("links", {}) and "gnss" in doc.get("links", {})
            held = hold_speed(bench, control, daemon_log, alive)
            if held:
                break
            # A stall of the one CPU latched an error on the way: the operator stops,
            # clears it (only that signature, see Operator) and starts over.
            document = status(control)
            why = {k: document.get(k) for k in ("mode", "faults", "fault_history")}
            assert operator.clear_stall(document, engaged=False), why
            assert ask(bench, {"op": "pedal", "pedal": "throttle", "pct": 0.0})["ok"]
            print(f"[husky] attempt {attempt + 1} ended by a stall; again")
        assert held, f"a stall ended every attempt: {operator.recoveries}"

        # The last half of the hold: the speed held near the locked one, on the throttle
        # board, inside the throttle limit, no brake.
        set_mps = float(status(control)["set_speed_mps"])
        late = held[len(held) // 2 :]
        speeds = [s["world"]["speed_mps"] for s in late]
        throttles = [
            s["throttle"]["command"]["position_pct"]
            for s in late
            if s["throttle"]["command"]["enable"]
        ]
        print(
            f"[husky] set {set_mps:.2f} m/s, held {statistics.median(speeds):.2f} m/s "
            f"(min {min(speeds):.2f}, max {max(speeds):.2f}), throttle median "
            f"{statistics.median(throttles) if throttles else 0:.1f} %"
        )
        assert LOCK_MPS - 0.3 <= set_mps <= LOCK_MPS + 0.6
        assert all(abs(v - set_mps) < 0.35 for v in speeds), speeds
        assert len(throttles) == len(late) and max(throttles) <= throttle_max_pct + 1e-6
        assert min(throttles) > 0.5  # the engine is working against drag
        brakes = [
            s["brake"]["command"]["position_pct"] if s["brake"]["command"]["enable"] else 0.0
            for s in late
        ]
        assert max(brakes) == 0.0, brakes  # never both pedals

        # A brake tap: back to ENGAGED, our throttle lets go, steering stays automatic.
        assert ask(bench, {"op": "brake_tap", "pct": 40.0, "duration_s": 0.3})["ok"]
        explained(
            slowly(lambda: status(control).get("mode") == "engaged", 0.2),
            5,
            "ENGAGED after a brake tap",
            daemon_log,
            alive,
        )
        wait_for(
            lambda: not observe(bench)["throttle"]["command"]["enable"],
            3,
            "the throttle released",
            daemon_log,
            alive,
        )
    finally:
        with contextlib.suppress(Exception):
            ask(bench, {"op": "pedal", "pedal": "throttle", "pct": 0.0})
        stop_all(procs)


def hold_speed(
    bench: Path, control: Path, log: Path, alive: tuple[subprocess.Popen[str], ...]
) -> list[dict[str, Any]]:
    """Engage, drive up to LOCK_MPS on the pedal, press +, let go, and observe HOLD_S of
    speed hold; [] when the mode left the sequence (a stall's error) on the way."""
    assert ask(bench, {"op": "press", "button": "engage"})["ok"]
    explained(
        slowly(lambda: status(control).get("mode") in ("engaged", "error"), 0.2),
        10,
        "ENGAGED",
        log,
        alive,
    )
    if status(control).get("mode") != "engaged":
        return []
    assert ask(bench, {"op": "pedal", "pedal": "throttle", "pct": 40.0})["ok"]
    wait_for(
        lambda: (
            observe(bench)["world"]["speed_mps"] >= LOCK_MPS
            or status(control).get("mode") != "engaged"
        ),
        60,
        "up to speed on the pedal",
        log,
        alive,
    )
    if status(control).get("mode") != "engaged":
        return []
    assert ask(bench, {"op": "press", "button": "speed_plus"})["ok"]
    explained(
        slowly(lambda: status(control).get("mode") in ("speed_hold", "error"), 0.2),
        5,
        "SPEED_HOLD",
        log,
        alive,
    )
    assert ask(bench, {"op": "pedal", "pedal": "throttle", "pct": 0.0})["ok"]
    samples: list[dict[str, Any]] = []
    started = time.monotonic()
    while time.monotonic() - started < HOLD_S:
        if status(control).get("mode") != "speed_hold":
            return []
        samples.append(observe(bench))
        time.sleep(0.2)
    return samples
