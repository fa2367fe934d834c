"""End to end over real SocketCAN: `dbw run` and the simulated vehicle in separate processes.

The daemon (simulation disabled, as on the vehicle) talks to the PC104 twin that `dbw sim`
runs on vcan0; candump (can-utils) records the bus and the log is checked with cantools
and an independent CRC, not with the daemon's code. Frames injected with cansend (a bad
CRC, a wrong length) are counted and survived; the interface going down and up is
recovered from without a restart.
"""

from __future__ import annotations

import itertools
import json
import re
import shutil
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
from drivers.pc104 import protocol
from tests.hil.test_pc104_vcan import crc8_sae_j1850_bitwise

pytestmark = pytest.mark.vcan

PROJECT_ROOT = Path(__file__).resolve().parents[2]
_LOG_LINE = re.compile(r"^\((?P<ts>\d+\.\d+)\) \S+ (?P<id>[0-9A-F]{3})#(?P<data>(?:[0-9A-F]{2})*)$")


def tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} not found: apt-get install can-utils iproute2", pytrace=False)
    return path


def dbw(*args: str, stdout: Any) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "appliance", "--log-format", "json", *args],
        cwd=PROJECT_ROOT,
        stdout=stdout,
        stderr=subprocess.STDOUT,
        text=True,
    )


def heartbeats(log: Path) -> list[dict[str, Any]]:
    """The heartbeat events the daemon has written so far. The log is read while the daemon
    writes it, and a long line reaches the file in more than one write: the text after the
    last newline is a line still being written, not a malformed one, and waits for the next
    read."""
    events = []
    complete = log.read_text().rpartition("\n")[0]
    for line in complete.splitlines():
        if line.startswith("{"):
            event = json.loads(line)
            if event.get("event") == "heartbeats":
                events.append(event)
    return events


def describe(proc: subprocess.Popen[str]) -> str:
    """``dbw run``, ``dbw sim`` or the program's name."""
    args = [str(a) for a in proc.args] if isinstance(proc.args, list) else [str(proc.args)]
    return f"dbw {args[5]}" if args[1:3] == ["-m", "appliance"] else Path(args[0]).name


def wait_for(
    condition: Callable[[], bool],
    timeout_s: float,
    what: str,
    log: Path,
    alive: tuple[subprocess.Popen[str], ...] = (),
    also: tuple[Path, ...] = (),
) -> None:
    start_s = time.monotonic()
    while not condition():
        dead = [p for p in alive if p.poll() is not None]
        waited_s = time.monotonic() - start_s
        if dead or waited_s > timeout_s:
            why = ", ".join(f"{describe(p)} exited {p.returncode}" for p in dead)
            tail = "\n".join(
                f"{path.name}:\n" + "\n".join(path.read_text().splitlines()[-15:])
                for path in (log, *also)
            )
            pytest.fail(
                f"gave up after {waited_s:.1f} s ({why or 'timed out'}) waiting for {what}:\n{tail}"
            )
        time.sleep(0.05)


def stop_all(procs: list[subprocess.Popen[str]]) -> None:
    """SIGTERM the processes still running, newest first; kill one that takes over 10 s."""
    for proc in reversed(procs):
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()


def pc104_link(log: Path) -> str:
    beats = heartbeats(log)
    return str(beats[-1]["links"]["pc104"]) if beats else ""


def counter(link: str, name: str) -> int:
    match = re.search(rf"{name}=(\d+)", link)
    return int(match.group(1)) if match else -1


def test_daemon_and_simulated_vehicle_over_vcan(vcan_channel: str, tmp_path: Path) -> None:
    dump_path, sim_log, daemon_log = (tmp_path / n for n in ("dump.log", "sim.log", "daemon.log"))
    sim_config = tmp_path / "via-sim.toml"
    procs: list[subprocess.Popen[str]] = []
    dump_out = dump_path.open("w")
    candump = subprocess.Popen([tool("candump"), "-L", vcan_channel], stdout=dump_out, text=True)
    procs.append(candump)
    try:
        with sim_log.open("w") as out:
            sim = dbw(
                "sim",
                "--can-channel",
                vcan_channel,
                "--write-config",
                str(sim_config),
                "--pty-dir",
                str(tmp_path / "ptys"),
                stdout=out,
            )
        procs.append(sim)
        wait_for(sim_config.exists, 30, "dbw sim to write its config", sim_log, (sim,))
        # Report link health five times a second so the test can follow it.
        settings = load_config(sim_config).model_dump(mode="json")
        settings["rates"]["status_report_hz"] = 5.0
        daemon_config = tmp_path / "daemon.toml"
        daemon_config.write_text(to_toml(settings) + "\n")
        with daemon_log.open("w") as out:
            daemon = dbw("run", "--config", str(daemon_config), stdout=out)
        procs.append(daemon)

        def link_up() -> bool:
            link = pc104_link(daemon_log)
            return link.startswith("up ") and "control=automatic" in link

        wait_for(link_up, 30, "the PC104 link to come up", daemon_log, (sim, daemon), (sim_log,))

        db = cantools.database.load_file(str(protocol.DBC_PATH))
        assert isinstance(db, cantools.database.can.Database)
        status = db.get_message_by_name("PC104_Status")
        bad_crc = bytes(status.length - 1) + bytes([0x00])
        if crc8_sae_j1850_bitwise(status.frame_id.to_bytes(2, "big") + bad_crc[:-1]) == 0:
            bad_crc = bad_crc[:-1] + b"\x01"
        subprocess.run(
            [tool("cansend"), vcan_channel, f"{status.frame_id:03X}#{bad_crc.hex().upper()}"],
            check=True,
        )
        subprocess.run([tool("cansend"), vcan_channel, f"{status.frame_id:03X}#0102"], check=True)
        wait_for(
            lambda: (
                counter(pc104_link(daemon_log), "crc") >= 1
                and counter(pc104_link(daemon_log), "malformed") >= 1
            ),
            10,
            "the injected frames to be counted",
            daemon_log,
        )
        assert daemon.poll() is None, "the daemon must survive malformed frames"

        ip = tool("ip")
        subprocess.run([ip, "link", "set", vcan_channel, "down"], check=True)
        wait_for(lambda: "STALE" in pc104_link(daemon_log), 10, "a stale status", daemon_log)
        subprocess.run([ip, "link", "set", vcan_channel, "up"], check=True)
        # candump exits when its interface goes down ("Network is down"): record on.
        candump.wait(timeout=5)
        candump = subprocess.Popen(
            [tool("candump"), "-L", vcan_channel], stdout=dump_out, text=True
        )
        procs.append(candump)
        wait_for(
            lambda: link_up() and "STALE" not in pc104_link(daemon_log),
            15,
            "the link to recover after the interface came back",
            daemon_log,
        )
        assert daemon.poll() is None

        daemon.send_signal(signal.SIGTERM)
        code = daemon.wait(timeout=10)
        tail = "\n".join(daemon_log.read_text().splitlines()[-15:])
        assert code == 0, f"daemon exit status {code}; log tail:\n{tail}"
    finally:
        stop_all(procs)
        dump_out.close()

    # The recorded bus, checked independently of the daemon's code.
    commands = db.get_message_by_name("HL_MotionCommand")
    by_id: dict[int, list[bytes]] = {}
    command_times_s: list[float] = []
    for line in dump_path.read_text().splitlines():
        match = _LOG_LINE.match(line)
        assert match is not None, line
        frame_id = int(match["id"], 16)
        by_id.setdefault(frame_id, []).append(bytes.fromhex(match["data"]))
        if frame_id == commands.frame_id:
            command_times_s.append(float(match["ts"]))
    sent = by_id.get(commands.frame_id, [])
    assert len(sent) >= 20, "the daemon commands the PC104"
    # At its control rate (50 Hz): the median gap, which the down/up outage cannot move.
    gaps_s = sorted(b - a for a, b in itertools.pairwise(command_times_s) if b > a)
    median_gap_s = gaps_s[len(gaps_s) // 2]
    assert 0.8 * 0.02 <= median_gap_s <= 2.5 * 0.02, median_gap_s
    patterns = set()
    steps_ok = 0
    previous = None
    for data in sent:
        assert len(data) == commands.length
        crc_input = commands.frame_id.to_bytes(2, "big") + data[:-1]
        assert data[-1] == crc8_sae_j1850_bitwise(crc_input), data.hex()
        values = commands.decode_simple(data, decode_choices=True)
        patterns.add(str(values["MotionPattern"]))
        value = int(commands.decode_simple(data, decode_choices=False)["Counter"])  # type: ignore[arg-type]
        if previous is not None and (value - previous) % 16 == 1:
            steps_ok += 1
        previous = value
    # Nothing is engaged: the daemon only ever asks the PC104 to stop.
    assert patterns == {"STOP"}, patterns
    # Rolling counter steps by one, apart from frames lost while the interface was down.
    assert steps_ok >= 0.95 * (len(sent) - 1)
    assert len(by_id.get(status.frame_id, [])) >= 20, "the twin's status reached the bus"
