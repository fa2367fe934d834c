"""The client's pure decisions: what command goes out, and the rate meter."""

from __future__ import annotations

import pytest

from drivers.pc104.client_core import RateMeter, command_to_send
from drivers.pc104.messages import ControlSource, MotionCommand, MotionPattern, Pc104Status

GO = MotionCommand(MotionPattern.STRAIGHT, 1.0)
STOP = MotionCommand.stop()
AUTO = Pc104Status(MotionPattern.STRAIGHT, True, ControlSource.AUTOMATIC)
CAB = Pc104Status(MotionPattern.STOP, False, ControlSource.CAB)
TIMEOUT_S = 0.1


@pytest.mark.parametrize(
    ("latest", "latest_s", "status", "fresh", "holding", "sent", "hold_after"),
    [
        (None, 0.0, AUTO, True, False, STOP, False),
        (GO, 1.0, AUTO, True, False, GO, False),
        (GO, 1.0 - TIMEOUT_S, AUTO, True, False, GO, False),  # exactly at the limit
        (GO, 0.8, AUTO, True, False, STOP, True),  # too old
        (GO, 1.0, AUTO, False, False, STOP, True),  # status stale
        (GO, 1.0, None, True, False, STOP, True),
        (GO, 1.0, CAB, True, False, STOP, True),  # cab in control
        (GO, 1.0, AUTO, True, True, STOP, True),  # holding until the loop sends STOP
        (STOP, 1.0, AUTO, True, True, STOP, False),  # the loop's STOP releases the hold
        (STOP, 0.0, None, False, False, STOP, False),
    ],
)
def test_command_to_send(
    latest: MotionCommand | None,
    latest_s: float,
    status: Pc104Status | None,
    fresh: bool,
    holding: bool,
    sent: MotionCommand,
    hold_after: bool,
) -> None:
    command, why, hold = command_to_send(latest, latest_s, 1.0, TIMEOUT_S, status, fresh, holding)
    assert (command, hold) == (sent, hold_after)
    assert bool(why) == (command is not latest)


def test_rate_meter_reports_the_last_full_window() -> None:
    meter = RateMeter(window_s=1.0)
    meter.update(0.0, 0)
    meter.update(0.5, 40)
    assert meter.rate_per_s == 0.0
    meter.update(1.0, 50)
    assert meter.rate_per_s == pytest.approx(50.0)
