"""End to end over real SocketCAN: an operator's session, with `dbw run` in its own process.

This test process is the vehicle: it runs the simulated world and every twin (scanners on
TCP, actuator boards on pseudo-terminals, the PC104 on vcan0) under a Supervisor in its own
event loop, so it can press the panel's buttons, push the throttle pedal, tap the brake,
hit the e-stop and make the PC104 go silent. The daemon (simulation disabled, as on the
vehicle) only sees those devices. The test follows the daemon's mode over the control
socket; candump (can-utils) records the bus, and the log is checked afterwards with
cantools and an independent CRC, not with the daemon's code: what the daemon commanded
the PC104 and announced in HL_Heartbeat, frame by frame, in order.

Allowances for the guest, none of them touching what is checked: user-mode Linux gives
both processes one CPU and, on a shared host, stalls them for tens of milliseconds at a
time (the daemon logged 100+ ms wake-up jitter). The sim profile's age limits (50 ms for
the steering pot) rightly call that a fault, so here every input age limit and the lower
layers' command timeouts are 0.5 s, the scanners run at 25 Hz and the test asks for
the daemon's status at 10 Hz (each query is CPU both processes need); how fast a stale
input is caught is tested in tests/unit/safety and measured by
benchmarks/bench_control.py. Waits are generous; the order of what reached the bus is
checked strictly, from the moment the daemon has settled in READY.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import itertools
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cantools
import pytest

from appliance.cli.sim import daemon_config
from appliance.config import VehicleConfig, load_config
from appliance.config.calibration_file import write_calibration
from appliance.config.loader import to_toml
from appliance.config.models import CanEndpoint
from appliance.config.simulated_calibration import simulated_calibration
from appliance.control_client import query
from appliance.control_protocol import ControlSocketError
from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.twins.pc104_core import Pc104TwinCore, TwinParams
from appliance.simulator import Simulator, build_simulator
from appliance.supervisor import Supervisor
from drivers.pc104 import protocol
from drivers.pc104.endpoint import CanInterface
from safety.watchdog import RestartPolicy
from tests.hil.test_pc104_vcan import crc8_sae_j1850_bitwise

pytestmark = pytest.mark.vcan

PROJECT_ROOT = Path(__file__).resolve().parents[2]
_LOG_LINE = re.compile(r"^\((?P<ts>\d+\.\d+)\) \S+ (?P<id>[0-9A-F]{3})#(?P<data>(?:[0-9A-F]{2})*)$")
COMMAND, HEARTBEAT = "HL_MotionCommand", "HL_Heartbeat"
# HL_Heartbeat.State from the settled READY on; the shutdown keeps STANDBY.
EXPECTED_STATES = [
    *("STANDBY", "ENGAGED"),  # READY, then engaged -> speed hold -> brake tap
    *("STANDBY", "ENGAGED"),  # manual override, engaged again
    *("FAULT", "STANDBY"),  # the PC104 silent: ERROR, override once it talks again
    *("FAULT", "STANDBY"),  # e-stop, released and reset
]
EXPECTED_COMMANDS = ["STOP", "MOVE", "STOP", "MOVE", "STOP"]  # MOVE: any pattern but STOP
THROTTLE_PEDAL_PCT = 30.0
SPEED_RESOLUTION_MPS = 0.001  # SpeedSetpoint's factor in the DBC
# While ENGAGED, the client may replace motion with STOP a cycle or so before the core
# itself sees the PC104 status go stale: at most this many frames, right before FAULT.
MAX_SUBSTITUTED_STOPS = 15
LIVENESS_S = 60.0  # the guest can fall seconds behind; nothing here needs that long
SETTLE_S = 2.0
GUEST_AGE_LIMIT_S = 0.5
# A status query is a round trip of 2.3 ms on the host (measured) and several times that
# in the guest, where every system call is trapped; both processes pay it out of the
# guest's one CPU, so the test polls at 10 Hz, not 20.
POLL_S = 0.1


def tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} not found: apt-get install can-utils iproute2", pytrace=False)
    return path


def free_tcp_ports(count: int) -> list[int]:
    """Ports for the scanner twins, so a `dbw sim` elsewhere on the host cannot collide."""
    with contextlib.ExitStack() as stack:
        socks = [stack.enter_context(socket.socket()) for _ in range(count)]
        for sock in socks:
            sock.bind(("127.0.0.1", 0))
        return [sock.getsockname()[1] for sock in socks]


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    # The control socket's path must fit sun_path (108 bytes); tmp_path can be longer.
    # TMPDIR, not /tmp: in the guest /tmp is the host's (hostfs), TMPDIR is a tmpfs.
    directory = Path(tempfile.mkdtemp(prefix="dbw-"))
    try:
        yield directory
    finally:
        shutil.rmtree(directory, ignore_errors=True)


def scenario_config(tmp_path: Path, socket_path: Path) -> VehicleConfig:
    data = load_config("sim").model_dump(mode="json")
    for side, port in zip(("left", "right"), free_tcp_ports(2), strict=True):
        data["devices"][f"lms111_{side}"] |= {"port": port, "scan_frequency_hz": 25}
    data["paths"]["control_socket"] = str(socket_path)
    data["rates"]["status_report_hz"] = 2.0  # the log tail a failure shows
    # The guest allowances (see the module docstring); the self-check may take a while.
    data["staleness"] = {name: GUEST_AGE_LIMIT_S for name in data["staleness"]}
    data["safety"]["lower_layer_command_timeout_s"] = GUEST_AGE_LIMIT_S
    data["supervision"]["control_heartbeat_deadline_s"] = 1.0
    data["engagement"]["self_check_timeout_s"] = 60.0
    path = tmp_path / "scenario.toml"
    path.write_text(to_toml(data) + "\n")
    return load_config(path)


# ---------------------------------------------------------------- the session


@dataclass
class Session:
    """The daemon seen through its control socket, and the twins the test operates."""

    simulator: Simulator
    socket_path: Path
    daemon: asyncio.subprocess.Process
    daemon_log: Path
    events: list[str] = field(default_factory=list)  # what the test did and saw, timed
    last_status: dict[str, Any] = field(default_factory=dict)

    @property
    def twins(self) -> ActuatorTwins:
        assert self.simulator.board_twins is not None
        return self.simulator.board_twins

    def note(self, what: str) -> None:
        self.events.append(f"{time.time():.3f} {what}")

    def detail(self) -> str:
        s = self.last_status
        keep = ("mode", "set_speed_mps", "measured_speed_mps", "last_refusal", "faults")
        summary = {k: s.get(k) for k in keep} | {"overrides": s.get("overrides")}
        tail = "\n".join(self.daemon_log.read_text().splitlines()[-12:])
        return (
            f"status: {summary}\ntest events:\n  "
            + "\n  ".join(self.events[-12:])
            + f"\ndaemon log tail:\n{tail}"
        )

    async def status(self) -> dict[str, Any] | None:
        try:
            reply = await query(self.socket_path, {"op": "status"}, timeout_s=5.0)
        except ControlSocketError:
            return None
        status = reply.get("status")
        if isinstance(status, dict):
            self.last_status = status
            return status
        return None

    async def wait_for(
        self,
        what: str,
        condition: Callable[[dict[str, Any]], bool],
        modes: set[str],
        timeout_s: float = LIVENESS_S,
    ) -> dict[str, Any]:
        """Poll the status until ``condition``; fail at once if the mode leaves ``modes``."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self.daemon.returncode is not None:
                pytest.fail(
                    f"the daemon exited ({self.daemon.returncode}) while waiting for "
                    f"{what}\n{self.detail()}"
                )
            status = await self.status()
            if status is not None:
                if status["mode"] not in modes:
                    pytest.fail(f"mode {status['mode']} while waiting for {what}\n{self.detail()}")
                if condition(status):
                    self.note(f"saw {what} (mode {status['mode']})")
                    return status
            if time.monotonic() > deadline:
                pytest.fail(f"gave up after {timeout_s} s waiting for {what}\n{self.detail()}")
            await asyncio.sleep(POLL_S)

    async def mode(self, mode: str, via: set[str]) -> dict[str, Any]:
        return await self.wait_for(mode, lambda s: s["mode"] == mode, via | {mode})

    async def stay(self, mode: str, seconds: float) -> None:
        """Stay in ``mode`` for ``seconds``, so the bus shows several heartbeats of it."""
        end_s = time.monotonic() + seconds
        await self.wait_for(f"{seconds} s in {mode}", lambda _: time.monotonic() > end_s, {mode})

    async def settled(self, mode: str) -> None:
        """Feet off the pedals, hands off the wheel, the vehicle at rest."""

        def still(s: dict[str, Any]) -> bool:
            speed = s["measured_speed_mps"]
            return not any(s["overrides"].values()) and speed is not None and abs(speed) < 0.05

        await self.wait_for(f"the vehicle at rest in {mode}", still, {mode})

    async def press(self, button: str, mode: str, via: set[str], again_after_s: float) -> None:
        """Press until the daemon is in ``mode``. Only for presses that are no-ops once
        they worked (engage when engaged, override when ready), so a press refused while
        the guest lagged (or while the e-stop was still being released) is repeated, as
        an operator would."""
        deadline_s = time.monotonic() + LIVENESS_S
        while True:
            self.note(f"press {button}")
            self.twins.panel.press(button)
            again_s = min(time.monotonic() + again_after_s, deadline_s)

            def done(s: dict[str, Any], again_s: float = again_s) -> bool:
                return s["mode"] == mode or time.monotonic() > again_s

            status = await self.wait_for(f"{mode} after {button}", done, via | {mode})
            if status["mode"] == mode:
                return
            if time.monotonic() > deadline_s:
                pytest.fail(
                    f"{button} pressed for {LIVENESS_S} s, still not {mode}\n" + self.detail()
                )

    async def settle(self) -> float:
        """READY, and staying so for SETTLE_S; returns when that stretch of READY began
        (wall clock, as candump's): the first status that showed it.

        A guest that has just started the daemon can stall both processes for longer
        than an input's age limit: a fault the daemon rightly raises, but not one of
        the scenario's. The operator clears it as on the vehicle (override, once the
        inputs are fresh again); the bus is checked strictly from the settled READY on,
        so its frames start with SETTLE_S of READY and STOP. (The end of the stretch
        would not do: the operator engages right after it, and in one census run the
        engagement's first motion command went out before the periodic STOP that would
        have followed the last READY heartbeat, so the strict part held no STOP at all.)
        """
        await self.mode("ready", {"boot", "self_check"})
        deadline_s = time.monotonic() + LIVENESS_S
        ready_since: tuple[float, float] | None = (time.monotonic(), time.time())
        while ready_since is None or time.monotonic() - ready_since[0] < SETTLE_S:
            if self.daemon.returncode is not None or time.monotonic() > deadline_s:
                pytest.fail(f"the daemon did not settle in READY\n{self.detail()}")
            status = await self.status()
            if status is not None and status["mode"] != "ready":
                faults = [f["key"] for f in status["faults"]]
                self.note(f"start-up: {status['mode']}, faults {faults}")
                if status["mode"] == "error" and not faults:
                    self.note("press manual_override: the start-up fault has cleared")
                    self.twins.panel.press("manual_override")
                ready_since = None
            elif status is not None and ready_since is None:
                ready_since = (time.monotonic(), time.time())  # the reply showed READY
            await asyncio.sleep(0.1)
        self.note("settled in READY: the strict part began with this stretch of READY")
        assert ready_since is not None  # the loop ends only in a long enough stretch
        return ready_since[1]


async def operate(session: Session) -> float:
    """The operator's session, from a settled READY; returns the set speed held."""
    twins, pc104 = session.twins, session.simulator.pc104_twin
    assert pc104 is not None

    await session.press("engage", "engaged", {"ready"}, again_after_s=5.0)
    session.note(f"throttle pedal {THROTTLE_PEDAL_PCT} %")
    twins.throttle.operator_pedal(THROTTLE_PEDAL_PCT)
    moving = await session.wait_for(
        "the vehicle moving", lambda s: (s["measured_speed_mps"] or 0.0) > 0.4, {"engaged"}
    )
    assert moving["overrides"]["throttle_pedal"], session.detail()
    session.note("press speed_plus (once: a second press would raise the set speed)")
    twins.panel.press("speed_plus")
    held = await session.mode("speed_hold", {"engaged"})
    set_speed_mps = float(held["set_speed_mps"])
    twins.throttle.operator_pedal(0.0)
    session.note(f"throttle pedal released, set speed {set_speed_mps} m/s")
    await session.stay("speed_hold", 1.5)

    session.note("brake tap")
    twins.brake.operator_brake_tap(40.0, 0.3)
    await session.mode("engaged", {"speed_hold"})
    await session.wait_for(
        "the brake tap over", lambda s: not any(s["overrides"].values()), {"engaged"}
    )
    await session.press("manual_override", "ready", {"engaged"}, again_after_s=5.0)
    await session.settled("ready")
    await session.stay("ready", 0.5)

    await session.press("engage", "engaged", {"ready"}, again_after_s=5.0)
    await session.stay("engaged", 0.5)
    session.note("PC104 twin silent")
    pc104.faults.drop_all = True  # until the daemon says ERROR, and at least 0.5 s
    silent_until_s = time.monotonic() + 0.5
    await session.mode("error", {"engaged"})
    await asyncio.sleep(max(silent_until_s - time.monotonic(), 0.0))
    pc104.faults.drop_all = False
    session.note("PC104 twin talking again")
    await session.wait_for("the fault cleared", lambda s: not s["faults"], {"error"})
    await session.press("manual_override", "ready", {"error"}, again_after_s=3.0)
    await session.stay("ready", 0.5)

    session.note("e-stop pressed")
    twins.panel.estop(True)
    await session.mode("estop", {"ready"})
    await session.stay("estop", 0.5)
    session.note("e-stop released")
    twins.panel.estop(False)
    await session.press("manual_override", "ready", {"estop"}, again_after_s=2.0)
    await session.stay("ready", 0.5)
    return set_speed_mps


# ---------------------------------------------------------------- the recorded bus


@dataclass(frozen=True)
class HlFrame:
    t_s: float
    name: str  # COMMAND or HEARTBEAT
    label: str  # the heartbeat's State; for a command "STOP" or "MOVE"
    pattern: str = ""
    speed_mps: float = 0.0


def read_hl_frames(dump: Path) -> list[HlFrame]:
    """Every HL frame of the log, each checked: length, CRC, counter +1 per identifier.
    PC104 frames (from the twin, some dropped on purpose) only for length and CRC."""
    db = cantools.database.load_file(str(protocol.DBC_PATH))
    assert isinstance(db, cantools.database.can.Database)
    hl: list[HlFrame] = []
    counters: dict[str, list[int]] = {COMMAND: [], HEARTBEAT: []}
    for line in dump.read_text().splitlines():
        match = _LOG_LINE.match(line)
        assert match is not None, f"unexpected candump line {line!r}"
        frame_id, data = int(match["id"], 16), bytes.fromhex(match["data"])
        message = db.get_message_by_frame_id(frame_id)
        assert len(data) == message.length, (message.name, data.hex())
        crc_input = frame_id.to_bytes(2, "big") + data[:-1]
        assert data[-1] == crc8_sae_j1850_bitwise(crc_input), (message.name, data.hex())
        if message.name not in counters:
            continue
        raw = message.decode_simple(data, decode_choices=False)
        counters[message.name].append(int(raw["Counter"]))  # type: ignore[arg-type]
        values = message.decode_simple(data, decode_choices=True)
        t_s = float(match["ts"])
        if message.name == HEARTBEAT:
            hl.append(HlFrame(t_s, HEARTBEAT, str(values["State"])))
        else:
            pattern = str(values["MotionPattern"])
            label = "STOP" if pattern == "STOP" else "MOVE"
            speed = float(values["SpeedSetpoint"])  # type: ignore[arg-type]
            hl.append(HlFrame(t_s, COMMAND, label, pattern, speed))
    for name, seen in counters.items():
        steps = {(b - a) % 16 for a, b in itertools.pairwise(seen)}
        assert steps == {1}, f"{name}: rolling counter steps {steps} (want +1 only)"
    return hl


def runs(labels: list[str]) -> list[tuple[str, int, int]]:
    """(label, first index, last index) of each stretch of equal labels."""
    out: list[tuple[str, int, int]] = []
    for i, label in enumerate(labels):
        if out and out[-1][0] == label:
            out[-1] = (label, out[-1][1], i)
        else:
            out.append((label, i, i))
    return out


def check_order(hl: list[HlFrame], start_s: float, set_speed_mps: float) -> None:
    """The frames from the settled READY on (and the heartbeat that announced it):
    exactly the session, in order."""
    beats = [f for f in hl if f.name == HEARTBEAT]
    cut_s = beats[max(bisect.bisect_left([b.t_s for b in beats], start_s) - 1, 0)].t_s
    beats = [b for b in beats if b.t_s >= cut_s]
    commands = [f for f in hl if f.name == COMMAND and f.t_s >= cut_s]
    state_runs = runs([b.label for b in beats])
    shown = [(label, round(beats[a].t_s, 2), round(beats[b].t_s, 2)) for label, a, b in state_runs]
    assert [r[0] for r in state_runs] == EXPECTED_STATES, shown

    command_runs = runs([c.label for c in commands])
    shown = [(label, b - a + 1, round(commands[a].t_s, 2)) for label, a, b in command_runs]
    assert [r[0] for r in command_runs] == EXPECTED_COMMANDS, shown
    assert {c.pattern for c in commands if c.label == "MOVE"} == {"COUNTER_STEER"}, shown

    # Each command against the heartbeats either side of it (the daemon sets both from
    # the same control cycle): motion only next to ENGAGED; STOP inside an ENGAGED
    # stretch only where the client stopped first, right before the PC104 fault.
    beat_times = [b.t_s for b in beats]
    substituted = 0
    for c in commands:
        i = bisect.bisect_right(beat_times, c.t_s)
        before = beats[i - 1].label if i > 0 else None
        after = next((b.label for b in beats[i:]), None)
        if c.label == "MOVE":
            assert "ENGAGED" in (before, after), (c, before, after)
        elif before == after == "ENGAGED":
            following = next(b.label for b in beats[i:] if b.label != "ENGAGED")
            assert following == "FAULT", (c, "STOP while ENGAGED, not before the fault")
            substituted += 1
    assert substituted <= MAX_SUBSTITUTED_STOPS, substituted

    # Speed: the operator's pedal forwarded, then exactly the set speed while held, then
    # nothing after the brake tap; the second engagement never asks for speed.
    _, first, last = command_runs[1]
    speeds = [c.speed_mps for c in commands[first : last + 1]]
    at_set = runs([str(abs(v - set_speed_mps) <= 1.5 * SPEED_RESOLUTION_MPS) for v in speeds])
    hold = max((r for r in at_set if r[0] == "True"), key=lambda r: r[2] - r[1], default=None)
    assert hold is not None and hold[2] - hold[1] + 1 >= 10, (set_speed_mps, at_set)
    before_hold, after_hold = speeds[: hold[1]], speeds[hold[2] + 1 :]
    assert before_hold and max(before_hold) > 0.3, before_hold[-20:]
    assert len(after_hold) >= 5 and set(after_hold) == {0.0}, after_hold[:20]
    _, first, last = command_runs[3]
    assert {c.speed_mps for c in commands[first : last + 1]} == {0.0}


# ---------------------------------------------------------------- the test


async def stop_process(proc: asyncio.subprocess.Process, sig: int = signal.SIGTERM) -> None:
    if proc.returncode is None:
        proc.send_signal(sig)
    try:
        await asyncio.wait_for(proc.wait(), 10.0)
    except TimeoutError:
        proc.kill()
        await proc.wait()


@pytest.mark.timeout(400)
async def test_operator_session_over_vcan(
    vcan_channel: str, tmp_path: Path, short_tmp: Path
) -> None:
    config = scenario_config(tmp_path, short_tmp / "control.sock")
    can = CanEndpoint(interface=CanInterface.SOCKETCAN, channel=vcan_channel)
    simulator = build_simulator(
        config, RestartPolicy(), can=can, pty_directory=str(tmp_path / "ptys")
    )
    pc104 = simulator.pc104_twin
    assert pc104 is not None  # its command timeout too, before it runs
    params = TwinParams(command_max_age_s=GUEST_AGE_LIMIT_S)
    pc104.core = Pc104TwinCore(pc104.world, params, now_s=time.monotonic())
    vehicle_root = asyncio.create_task(Supervisor(simulator.services).run(), name="vehicle")
    dump_path, daemon_log = tmp_path / "candump.log", tmp_path / "daemon.log"
    procs: list[asyncio.subprocess.Process] = []
    try:
        with dump_path.open("w") as dump_out:
            candump = await asyncio.create_subprocess_exec(
                tool("candump"), "-L", vcan_channel, stdout=dump_out
            )
        procs.append(candump)
        deadline = time.monotonic() + LIVENESS_S
        while not dump_path.read_text():  # the PC104 twin talks: candump is recording
            assert time.monotonic() < deadline, "candump recorded nothing"
            await asyncio.sleep(0.05)

        calibration_file = tmp_path / "daemon.calibration.toml"
        write_calibration(calibration_file, simulated_calibration(f"{config.name}-via-dbw-sim"))
        vehicle_file = tmp_path / "daemon.toml"
        vehicle_file.write_text(daemon_config(config, simulator, can, calibration_file))
        with daemon_log.open("w") as out:
            daemon = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "appliance",
                "--log-format",
                "json",
                "run",
                "--config",
                str(vehicle_file),
                cwd=PROJECT_ROOT,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        procs.append(daemon)
        session = Session(simulator, Path(config.paths.control_socket), daemon, daemon_log)
        start_s = await session.settle()
        set_speed_mps = await operate(session)

        session.note("SIGTERM")
        daemon.send_signal(signal.SIGTERM)
        code = await asyncio.wait_for(daemon.wait(), 30.0)
        assert code == 0, f"daemon exit status {code}\n{session.detail()}"
        await asyncio.sleep(0.2)  # the last frames in flight
    finally:
        for proc in reversed(procs):  # the daemon (if the session failed), then candump
            await stop_process(proc, signal.SIGINT if proc is candump else signal.SIGTERM)
        vehicle_root.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.wait_for(vehicle_root, 5.0)
        simulator.close()

    hl = read_hl_frames(dump_path)
    try:
        check_order(hl, start_s, set_speed_mps)
    except AssertionError as exc:
        events = "\n  ".join(session.events)
        raise AssertionError(f"{exc}\ntest events:\n  {events}") from exc
