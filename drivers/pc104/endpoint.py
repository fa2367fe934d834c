"""Where the PC104 link's bus is and how to open it: the interface kinds and their limits.

These are python-can's interfaces as this kit uses them, so they belong to the driver;
a vehicle file's ``devices.can`` section names one of them, and the driver reads that
section through :class:`BusEndpoint` without knowing the file.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Protocol


class CanInterface(StrEnum):
    SOCKETCAN = "socketcan"  # the vehicle, and vcan in HIL tests
    # A USB-CAN adapter speaking SLCAN on a serial port (channel: the tty); also how the
    # built-in simulated vehicle's own process reaches the daemon.
    SLCAN = "slcan"
    VIRTUAL = "virtual"  # python-can's in-process bus: unit tests and an inline simulation


# The bit rates an SLCAN adapter can be told (Lawicel S0..S8).
SLCAN_BITRATES_BPS = (
    10_000,
    20_000,
    50_000,
    100_000,
    125_000,
    250_000,
    500_000,
    750_000,
    1_000_000,
)


class BusEndpoint(Protocol):
    """What the driver reads to open the bus."""

    @property
    def interface(self) -> CanInterface: ...

    @property
    def channel(self) -> str: ...

    @property
    def bitrate_bps(self) -> int: ...
