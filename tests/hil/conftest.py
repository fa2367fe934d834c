"""Fixtures for the hardware-in-the-loop (HIL) tests.

These tests exist to exercise the real SocketCAN path (kernel CAN_RAW sockets on a
vcan interface, python-can's ``socketcan`` backend, can-utils as an independent peer),
which the in-process ``virtual`` bus used by the unit tests cannot cover. A HIL test
that quietly skips is worse than none, so a missing vcan0 is a hard failure here:
run them through ``tools/vcan_run.py``, which boots user-mode Linux when the host
kernel has no CAN support.
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

VCAN_CHANNEL = "vcan0"
_IFF_UP = 0x1
_HOW_TO_RUN = (
    "run them with `.venv/bin/python tools/vcan_run.py`, which uses user-mode Linux "
    "when the host kernel has no CAN support"
)


def _vcan_problem(channel: str) -> str | None:
    """Return why ``channel`` cannot carry CAN frames, or None when it can."""
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except (AttributeError, OSError) as exc:
        return f"this kernel has no SocketCAN (socket(AF_CAN) failed: {exc})"
    with sock:
        try:
            sock.bind((channel,))
        except OSError as exc:
            return f"cannot bind a CAN_RAW socket to {channel} ({exc})"
    try:
        flags = int(Path("/sys/class/net", channel, "flags").read_text(), 16)
    except (OSError, ValueError) as exc:
        return f"cannot read the interface flags of {channel} ({exc})"
    if not flags & _IFF_UP:
        return f"{channel} exists but is down (ip link set up {channel})"
    return None


@pytest.fixture(scope="session")
def vcan_channel() -> str:
    """The name of a SocketCAN vcan interface that is up; fails (never skips) otherwise."""
    problem = _vcan_problem(VCAN_CHANNEL)
    if problem is not None:
        pytest.fail(
            f"vcan tests need a real SocketCAN {VCAN_CHANNEL}: {problem}; {_HOW_TO_RUN}",
            pytrace=False,
        )
    return VCAN_CHANNEL
