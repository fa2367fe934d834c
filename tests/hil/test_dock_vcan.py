"""A whole docking approach over real SocketCAN: `dbw run` and `dbw sim` in separate processes.

The simulated flat-bed starts 3 m in front of its launcher, off the axis and turned; the
daemon (simulation disabled, as on the vehicle) reads the two LMS111 twins over TCP and
talks to the PC104 twin on vcan0, which closes the steering loop itself on the pose frames
(``docking.pose_loop = "pc104"``). The operator holds the engage button and the throttle
pedal through the bench socket. candump records the bus, and the log is read with cantools
and an independent CRC, not with the daemon's code: the motion patterns in their order, the
pose and expected pose frames, the PC104's own report, and a stop at the troughs.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cantools
import pytest

from appliance.config import load_config
from appliance.config.loader import to_toml
from appliance.control_client import ControlClient
from appliance.control_protocol import ControlSocketError
from appliance.guidance.docking import DockingParams, teeth_inside
from drivers.geometry import Pose2D
from drivers.pc104 import protocol
from tests.hil.test_daemon_vcan import _LOG_LINE, PROJECT_ROOT, dbw, stop_all, tool, wait_for
from tests.hil.test_pc104_vcan import crc8_sae_j1850_bitwise
from tests.runtime.inline import free_port

START_GAP_M = 3.0
DOCK_TIMEOUT_S = 200.0  # about 45 s on an idle machine; user-mode Linux is slower

pytestmark = [pytest.mark.vcan, pytest.mark.timeout(DOCK_TIMEOUT_S + 200.0)]


def as_the_service_runs_it() -> None:
    """The daemon's priority under systemd (``Nice=-5`` in systemd/dbw.service), above the
    simulated vehicle's: on one CPU the control loop must not wait for the renderer, as on
    the vehicle it does not wait for anything else. Not permitted: the default."""
    with contextlib.suppress(PermissionError):
        os.nice(-5)


def start_daemon(config: Path, log: Path) -> subprocess.Popen[str]:
    """`dbw run --config CONFIG` as the service runs it, its JSON log into ``log``."""
    with log.open("w") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "appliance", "--log-format", "json", "run", "--config",
             str(config)],
            cwd=PROJECT_ROOT, stdout=out, stderr=subprocess.STDOUT, text=True,
            preexec_fn=as_the_service_runs_it,
        )  # fmt: skip


def ask(path: Path, request: dict[str, Any]) -> dict[str, Any]:
    """One request on a control or bench socket (each its own connection)."""

    async def call() -> dict[str, Any]:
        async with ControlClient(path, timeout_s=5.0) as client:
            return await client.call(request)

    return asyncio.run(call())


def status(control: Path) -> dict[str, Any]:
    try:
        reply = ask(control, {"op": "status"})
    except (OSError, TimeoutError, ControlSocketError):  # the daemon is not listening yet
        return {}
    return dict(reply.get("status", {}))


def slowly(condition: Callable[[], bool], period_s: float = 0.5) -> Callable[[], bool]:
    """``condition`` asked at most every ``period_s``: each question is two socket round
    trips and an event loop, and in user-mode Linux the daemon and the simulated vehicle
    share one CPU with this test."""

    def asked() -> bool:
        time.sleep(max(period_s - 0.05, 0.0))  # wait_for sleeps the other 50 ms
        return condition()

    return asked


def explained(
    condition: Callable[[], bool],
    timeout_s: float,
    what: str,
    log: Path,
    alive: tuple[subprocess.Popen[str], ...],
    phases: list[str] | None = None,
) -> None:
    """``wait_for``, and on failure what the daemon says: faults come and go within a
    second, so the log's last lines rarely show the one that stopped the vehicle."""
    try:
        wait_for(condition, timeout_s, what, log, alive)
    except pytest.fail.Exception as exc:
        document = status(log.with_name("control.sock"))
        why = {k: document.get(k) for k in ("mode", "faults", "fault_history", "autopilot")}
        pytest.fail(f"{exc}\nphases so far: {phases}\nstatus: {why}", pytrace=False)


def docking(document: dict[str, Any]) -> dict[str, Any]:
    return dict(document.get("autopilot", {}).get("docking", {}))


def one_cpu_allowances(data: dict[str, Any]) -> None:
    """What a vehicle file needs to run its daemon and simulated vehicle on one CPU.

    User-mode Linux gives the daemon, the simulated vehicle, candump and the test one
    CPU, on which the two processes alone need nearly all of it (measured: 47 % and 51 %
    idling in front of the launcher, against 26 % and 29 % on the host). So the scanners
    run at 25 Hz with 0.5° (a mode the LMS111 has; half the beams to render and to
    read), the control loop runs at 25 Hz (the PC104's frames stay at 50 Hz), and the
    age limits allow the scheduling of that one CPU: what these tests are about is the
    path between two processes, and the limits have their own tests. The lower layers'
    command timeout goes with them (the PC104 twin's and the boards'): a stall of that
    CPU delays the daemon's commands as it delays every frame (seen in a fresh clone: a
    PC104 command_timeout 0.31 m from the troughs, cleared in 38 ms).
    """
    data["rates"]["control_hz"] = 25.0
    for side in ("lms111_left", "lms111_right"):
        data["devices"][side]["angular_resolution_deg"] = 0.5
    data["staleness"] |= {
        "scan_max_age_s": 0.3,
        "pc104_status_max_age_s": 0.3,
        "steering_pot_max_age_s": 0.2,
        "actuator_board_max_age_s": 0.3,
        "panel_max_age_s": 0.4,
    }
    data["safety"]["lower_layer_command_timeout_s"] = 0.3


def sim_config(tmp_path: Path) -> Path:
    config = load_config("flatbed-sim")
    data = config.model_dump(mode="json")
    data["devices"]["lms111_left"]["port"] = free_port()
    data["devices"]["lms111_right"]["port"] = free_port()
    front_forward_m = config.geometry.length_m / 2.0
    data["simulation"] |= {
        "start_x_m": -START_GAP_M - front_forward_m,
        "start_y_m": 0.12,
        "start_yaw_deg": 1.0,
    }
    data["docking"]["pose_loop"] = "pc104"
    one_cpu_allowances(data)
    data["paths"]["control_socket"] = str(tmp_path / "control.sock")
    data["rates"]["status_report_hz"] = 2.0
    path = tmp_path / "flatbed.toml"
    path.write_text(to_toml(data) + "\n")
    return path


# How many times the operator may clear an error the whole machine caused by stalling.
STALL_RECOVERIES = 2
# The PC104's side of the same stall: our commands reached it late.
STALL_PC104_DETAIL = "PC104 reports command_timeout"


class Operator:
    """Clears an error that a stall of the one shared CPU latched, as an operator would.

    User-mode Linux runs the daemon, the simulated vehicle, candump and this test on one
    CPU of the host, and a host that is busy elsewhere can stop all of them at once for
    a few hundred milliseconds (seen in CI: every input 400-412 ms old at one instant and
    fresh 15 ms later, the devices having kept talking). The daemon is right to latch
    that as an error: its loop did not run (or, seen from the PC104, our commands came
    late: a ``command_timeout`` it reports). What the operator does then is what the mode
    machine asks: manual override once the faults are gone, then engage again. Only that
    signature is cleared, at most ``STALL_RECOVERIES`` times, each one printed; any other
    error, or a fault still active, stays a failure.
    """

    def __init__(self, bench: Path) -> None:
        self.bench = bench
        self.recoveries: list[list[str]] = []

    def clear_stall(self, document: dict[str, Any], engaged: bool) -> bool:
        """True if it cleared a stall's error (and re-engaged when ``engaged``)."""
        if document.get("mode") != "error" or document.get("faults"):
            return False
        history = document.get("fault_history") or []
        if not history or len(self.recoveries) >= STALL_RECOVERIES:
            return False
        last_raised = max(float(f["raised_s"]) for f in history)
        burst = [f for f in history if last_raised - float(f["raised_s"]) < 0.1]
        stall = all(
            (str(f["key"]).startswith("stale:") or f.get("detail") == STALL_PC104_DETAIL)
            and f.get("cleared_s") is not None
            and float(f["cleared_s"]) - float(f["raised_s"]) < 1.0
            for f in burst
        )
        if not stall:
            return False
        self.recoveries.append([str(f["detail"]) for f in burst])
        print(f"[dock over vcan] a stall latched an error, cleared by the operator: {burst}")
        assert ask(self.bench, {"op": "press", "button": "manual_override"})["ok"]
        if engaged:
            hold = {"op": "hold", "button": "engage", "seconds": DOCK_TIMEOUT_S + 30}
            assert ask(self.bench, hold)["ok"]
        return True


def collapsed(values: list[str]) -> list[str]:
    return [v for i, v in enumerate(values) if i == 0 or values[i - 1] != v]


def test_a_docking_approach_over_vcan(vcan_channel: str, tmp_path: Path) -> None:
    dump_path, sim_log, daemon_log = (tmp_path / n for n in ("dump.log", "sim.log", "daemon.log"))
    daemon_config, bench, control = (
        tmp_path / "daemon.toml",
        tmp_path / "bench.sock",
        tmp_path / "control.sock",
    )
    procs: list[subprocess.Popen[str]] = []
    dump_out = dump_path.open("w")
    procs.append(
        subprocess.Popen([tool("candump"), "-L", vcan_channel], stdout=dump_out, text=True)
    )
    phases: list[str] = []
    try:
        with sim_log.open("w") as out:
            sim = dbw(
                "sim",
                "--config",
                str(sim_config(tmp_path)),
                "--can-channel",
                vcan_channel,
                "--write-config",
                str(daemon_config),
                "--pty-dir",
                str(tmp_path / "ptys"),
                "--bench-socket",
                str(bench),
                stdout=out,
            )
        procs.append(sim)
        wait_for(daemon_config.exists, 60, "dbw sim to write its config", sim_log, (sim,))
        daemon = start_daemon(daemon_config, daemon_log)
        procs.append(daemon)

        operator = Operator(bench)

        def engageable() -> bool:
            document = status(control)
            operator.clear_stall(document, engaged=False)
            return document.get("mode") == "ready" and not document.get("engage_blockers")

        explained(
            slowly(engageable), 90, "the launcher in view, engageable", daemon_log, (sim, daemon)
        )
        assert ask(bench, {"op": "hold", "button": "engage", "seconds": DOCK_TIMEOUT_S + 30})["ok"]
        assert ask(bench, {"op": "pedal", "pedal": "throttle", "pct": 100.0})["ok"]

        def docked() -> bool:
            document = status(control)
            operator.clear_stall(document, engaged=True)
            phase = str(docking(document).get("phase", ""))
            if phase and (not phases or phases[-1] != phase):
                phases.append(phase)
            moving = abs(ask(bench, {"op": "observe"})["state"]["world"]["speed_mps"]) > 0.005
            return phase == "docked" and not moving

        explained(
            slowly(docked), DOCK_TIMEOUT_S, "docked and stopped", daemon_log, (sim, daemon), phases
        )
        world = ask(bench, {"op": "observe"})["state"]["world"]
        final = status(control)
        assert final.get("mode") == "engaged", final.get("faults")
        assert ask(bench, {"op": "pedal", "pedal": "throttle", "pct": 0.0})["ok"]

        daemon.send_signal(signal.SIGTERM)
        code = daemon.wait(timeout=15)
        assert code == 0, "\n".join(daemon_log.read_text().splitlines()[-15:])
    finally:
        stop_all(procs)
        dump_out.close()

    # Where the vehicle is, from the simulated world: both teeth in their troughs.
    config = load_config("flatbed-sim")
    truth = Pose2D(world["x_m"], world["y_m"], world["platform_yaw_rad"])
    assert teeth_inside(truth, DockingParams(front_end_forward_m=config.geometry.length_m / 2))
    assert abs(math.degrees(world["platform_yaw_rad"])) < 0.3, world
    assert phases[0] == "heading" and phases[-1] == "docked", phases

    # The bus, read independently of the daemon's code.
    db = cantools.database.load_file(str(protocol.DBC_PATH))
    assert isinstance(db, cantools.database.can.Database)
    frames: dict[str, list[dict[str, Any]]] = {}
    for line in dump_path.read_text().splitlines():
        match = _LOG_LINE.match(line)
        assert match is not None, line
        frame_id, data = int(match["id"], 16), bytes.fromhex(match["data"])
        message = db.get_message_by_frame_id(frame_id)
        assert len(data) == message.length, line
        assert data[-1] == crc8_sae_j1850_bitwise(frame_id.to_bytes(2, "big") + data[:-1]), line
        values = message.decode_simple(data, decode_choices=True)
        named = {k: v.name if hasattr(v, "name") else v for k, v in values.items()}
        frames.setdefault(message.name, []).append(named)

    patterns = collapsed([str(f["MotionPattern"]) for f in frames["HL_MotionCommand"]])
    print(f"[dock over vcan] truth {truth}, patterns {patterns}, phases {phases}")
    # The paper's steps in order: heading by rear steer, oblique to the axis, straight in,
    # stop; corrections in between allowed, chattering not. A stall the operator cleared
    # stopped the vehicle and resumed the pattern it was in: two more entries each.
    assert patterns[0] == "STOP" and patterns[-1] == "STOP", patterns
    steps = iter(patterns)
    assert all(step in steps for step in ("REAR_STEER", "OBLIQUE", "STRAIGHT", "STOP")), patterns
    assert len(patterns) <= 2 + 6 + 2 * len(operator.recoveries), (patterns, operator.recoveries)

    poses = frames["HL_Pose"]
    assert len(poses) > 50 * 20, len(poses)  # 50 Hz through the approach
    trusted = [p for p in poses if p["PoseState"] == "OK"]
    assert len(trusted) > 0.9 * len(poses)
    last = poses[-1]
    assert last["PoseX"] == pytest.approx(-6.0, abs=0.03), last  # the docked centre
    assert abs(float(last["PoseY"]) - truth.y_m) < 0.01, (last, truth)
    expected = frames["HL_ExpectedPose"]
    assert {
        (e["SteeringLoop"], round(e["ExpectedX"], 3), round(e["ExpectedY"], 3)) for e in expected
    } == {("PC104", -6.0, 0.0)}

    statuses = frames["PC104_Status"]
    assert not any(s["FaultPose"] for s in statuses), "the pose never went missing"
    active = collapsed([str(s["ActivePattern"]) for s in statuses])
    assert "REAR_STEER" in active and "OBLIQUE" in active and active[-1] == "STOP", active
    assert abs(float(statuses[-1]["MeasuredSpeed"])) < 0.005
    # And the twin steered the rear row by itself: its encoder moved in REAR_STEER.
    assert max(abs(float(w["Row4Angle"])) for w in frames["PC104_WheelAngles"]) > math.radians(0.2)
