"""SocketCAN error frames: what the local CAN controller says about the bus.

python-can delivers them as ordinary messages with ``is_error_frame`` set (socketcan
enables them with ``CAN_RAW_ERR_FILTER`` unless told otherwise); the error class is in the
identifier and the details in the payload, as ``linux/can/error.h`` defines. Many
interfaces never implement ``bus.state`` (python-can returns ACTIVE for socketcan
whatever the controller does), so these frames are how bus-off and error-passive become
visible. Pure functions; the twin uses :func:`error_frame` to play the controller on a
``virtual`` bus, which has no controller of its own.
"""

from __future__ import annotations

from enum import IntEnum

# Error classes: the identifier of an error frame (linux/can/error.h).
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004  # details in data[1]
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100
CAN_ERR_CNT = 0x200  # TX/RX error counters in data[6], data[7]

# Controller status, data[1] of a CAN_ERR_CRTL frame.
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40

ERROR_FRAME_LENGTH = 8


class BusCondition(IntEnum):
    """The controller's error state, ordered from good to bad."""

    ACTIVE = 0
    WARNING = 1
    PASSIVE = 2
    BUS_OFF = 3


def bus_condition(error_class: int, data: bytes) -> BusCondition | None:
    """The controller state an error frame announces, or None if it only reports a
    protocol error (lost arbitration, missing ACK, ...) without a state change."""
    if error_class & CAN_ERR_BUSOFF:
        return BusCondition.BUS_OFF
    if error_class & CAN_ERR_RESTARTED:
        return BusCondition.ACTIVE
    if error_class & CAN_ERR_CRTL and len(data) > 1:
        status = data[1]
        if status & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE):
            return BusCondition.PASSIVE
        if status & (CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING):
            return BusCondition.WARNING
        if status & CAN_ERR_CRTL_ACTIVE:
            return BusCondition.ACTIVE
    return None


def error_frame(condition: BusCondition) -> tuple[int, bytes]:
    """The (error class, payload) a SocketCAN driver sends when entering ``condition``."""
    data = bytearray(ERROR_FRAME_LENGTH)
    if condition is BusCondition.BUS_OFF:
        return CAN_ERR_BUSOFF, bytes(data)
    if condition is BusCondition.ACTIVE:
        return CAN_ERR_RESTARTED, bytes(data)
    data[1] = {
        BusCondition.WARNING: CAN_ERR_CRTL_TX_WARNING,
        BusCondition.PASSIVE: CAN_ERR_CRTL_TX_PASSIVE,
    }[condition]
    return CAN_ERR_CRTL, bytes(data)
