"""Smoke tests of the real SocketCAN path: python-can against can-utils on vcan0.

can-utils (``candump``, ``cansend``) is an independent implementation of the other end,
so these tests catch mistakes that a python-can-to-python-can loop would hide (ID
width, extended flag, DLC, byte order of the payload). Every wait has a short timeout
so that a broken setup fails in seconds, not at the pytest-timeout limit.
"""

from __future__ import annotations

import queue
import re
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import can
import pytest

pytestmark = pytest.mark.vcan

STEP_TIMEOUT_S = 5.0
SYNC_ID = 0x7FF  # sent until candump shows it: proves candump is listening
END_ID = 0x7FE  # sent after the payload: once candump shows it, it has seen everything

# candump -L: "(1700000000.123456) vcan0 123#DEADBEEF"; 3 hex digits = standard, 8 = extended.
_LOG_LINE = re.compile(
    r"^\(\d+\.\d+\) (?P<channel>\S+) (?P<id>[0-9A-F]{3}|[0-9A-F]{8})#(?P<data>(?:[0-9A-F]{2})*)$"
)

Frame = tuple[int, bool, bytes]  # (arbitration_id, is_extended_id, data)


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} not found on PATH: apt-get install can-utils", pytrace=False)
    return path


class CandumpLog:
    """Frames that a running ``candump -L`` printed, parsed as a reader thread delivers them."""

    def __init__(self, proc: subprocess.Popen[str], channel: str) -> None:
        self.proc = proc
        self.channel = channel
        self.frames: list[Frame] = []
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line.rstrip("\n"))

    def wait_for(self, arbitration_id: int, timeout_s: float) -> bool:
        """Parse output until a frame with ``arbitration_id`` shows up; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                line = self._lines.get(timeout=remaining)
            except queue.Empty:
                break
            match = _LOG_LINE.match(line)
            assert match is not None, f"unexpected candump output: {line!r}"
            assert match["channel"] == self.channel, line
            frame = (int(match["id"], 16), len(match["id"]) == 8, bytes.fromhex(match["data"]))
            self.frames.append(frame)
            if frame[0] == arbitration_id:
                return True
        return False


@contextmanager
def candump(channel: str) -> Iterator[CandumpLog]:
    proc = subprocess.Popen(
        [_tool("candump"), "-L", channel],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        yield CandumpLog(proc, channel)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=STEP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


SENT: list[Frame] = [
    (0x000, False, b""),
    (0x123, False, bytes.fromhex("DEADBEEF")),
    (0x456, False, bytes.fromhex("0011223344556677")),
    (0x00000005, True, bytes.fromhex("A5")),
    (0x1ABCDE00, True, bytes.fromhex("0102")),
    (0x1FFFFFFF, True, bytes.fromhex("FFEEDDCCBBAA99")),
]


@pytest.mark.timeout(30)
def test_python_can_frames_reach_candump(vcan_channel: str) -> None:
    with (
        can.Bus(interface="socketcan", channel=vcan_channel) as bus,
        candump(vcan_channel) as dump,
    ):
        deadline = time.monotonic() + STEP_TIMEOUT_S
        while True:
            bus.send(can.Message(arbitration_id=SYNC_ID, is_extended_id=False, data=b"sync"))
            if dump.wait_for(SYNC_ID, 0.1):
                break
            if time.monotonic() > deadline:
                pytest.fail(f"candump never printed the sync frame (exit code {dump.proc.poll()})")
        for arbitration_id, is_extended_id, data in SENT:
            bus.send(
                can.Message(arbitration_id=arbitration_id, is_extended_id=is_extended_id, data=data)
            )
        bus.send(can.Message(arbitration_id=END_ID, is_extended_id=False, data=b"end"))
        assert dump.wait_for(END_ID, STEP_TIMEOUT_S), f"no end frame; candump saw {dump.frames}"

    # Extra sync frames may have been in flight when candump first showed one; they
    # all precede the payload, so take everything after the last one.
    last_sync = max(i for i, frame in enumerate(dump.frames) if frame[0] == SYNC_ID)
    assert dump.frames[last_sync + 1 : -1] == SENT
    assert dump.frames[-1] == (END_ID, False, b"end")


@pytest.mark.timeout(30)
def test_cansend_frames_reach_python_can(vcan_channel: str) -> None:
    cases: list[tuple[str, Frame]] = [
        ("123#DEADBEEF", (0x123, False, bytes.fromhex("DEADBEEF"))),
        ("1ABCDE00#0102", (0x1ABCDE00, True, bytes.fromhex("0102"))),
        ("00000005#", (0x5, True, b"")),
    ]
    # The bus is bound before cansend runs, so no frame can be missed.
    with can.Bus(interface="socketcan", channel=vcan_channel) as bus:
        for spec, (arbitration_id, is_extended_id, data) in cases:
            subprocess.run(
                [_tool("cansend"), vcan_channel, spec],
                check=True,
                timeout=STEP_TIMEOUT_S,
                capture_output=True,
            )
            msg = bus.recv(timeout=STEP_TIMEOUT_S)
            assert msg is not None, f"python-can received nothing after cansend {spec}"
            assert msg.arbitration_id == arbitration_id, spec
            assert msg.is_extended_id is is_extended_id, spec
            assert bytes(msg.data) == data, spec
            assert msg.dlc == len(data), spec
            assert not msg.is_remote_frame, spec
            assert not msg.is_error_frame, spec
            assert not msg.is_fd, spec
            assert msg.channel == vcan_channel, spec
