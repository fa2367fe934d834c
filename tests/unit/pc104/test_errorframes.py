"""SocketCAN error frames to controller states."""

from __future__ import annotations

import pytest

from drivers.pc104.errorframes import (
    CAN_ERR_ACK,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_ACTIVE,
    CAN_ERR_CRTL_RX_PASSIVE,
    CAN_ERR_CRTL_RX_WARNING,
    CAN_ERR_LOSTARB,
    BusCondition,
    bus_condition,
    error_frame,
)


@pytest.mark.parametrize("condition", list(BusCondition))
def test_the_frames_the_twin_emits_read_back_as_their_condition(condition: BusCondition) -> None:
    assert bus_condition(*error_frame(condition)) is condition


@pytest.mark.parametrize(
    ("error_class", "status", "expected"),
    [
        (CAN_ERR_CRTL, CAN_ERR_CRTL_RX_PASSIVE, BusCondition.PASSIVE),
        (CAN_ERR_CRTL, CAN_ERR_CRTL_RX_WARNING, BusCondition.WARNING),
        (CAN_ERR_CRTL, CAN_ERR_CRTL_ACTIVE, BusCondition.ACTIVE),
        (CAN_ERR_CRTL, 0x00, None),
        (CAN_ERR_ACK, 0x00, None),
        (CAN_ERR_LOSTARB, 0x00, None),
    ],
)
def test_controller_status(error_class: int, status: int, expected: BusCondition | None) -> None:
    assert bus_condition(error_class, bytes([0, status, 0, 0, 0, 0, 0, 0])) is expected


def test_short_error_frames_do_not_crash() -> None:
    assert bus_condition(CAN_ERR_CRTL, b"") is None
