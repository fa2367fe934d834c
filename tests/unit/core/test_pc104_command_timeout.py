"""A PC104 that has not heard us yet: not a fault before we actuate, a fault while we do.

Every PC104 reports ``FaultCommandTimeout`` from power-on until the high level's first
commands arrive; the daemon used to go to ERROR on it whenever the PC104's status came up
before its commands got through (seen with the simulated vehicle in its own process).
"""

from __future__ import annotations

from appliance.modes import Mode
from drivers.actuators.messages import Buttons
from drivers.pc104.messages import Pc104Faults
from tests.unit.core.test_core import assert_released, assert_safe, bench, events, speed_hold


def test_command_timeout_before_engagement_is_no_fault_but_blocks_engagement() -> None:
    core, vehicle = bench()
    vehicle.pc104_faults = Pc104Faults(command_timeout=True)
    out = vehicle.step(core)
    assert out.mode is Mode.READY
    assert not events(out, "fault_raised")
    assert_released(out)
    vehicle.press(Buttons.ENGAGE)
    out = vehicle.step(core)
    assert out.mode is Mode.READY
    reasons = events(out, "engage_refused")[0]["reasons"]
    assert any("PC104 not ready" in r for r in reasons), reasons
    # Our commands get through: the PC104 clears the flag and engagement is allowed.
    vehicle.pc104_faults = Pc104Faults()
    vehicle.step(core)
    vehicle.press(Buttons.ENGAGE)
    assert vehicle.step(core).mode is Mode.ENGAGED


def test_command_timeout_while_actuating_is_a_fault_in_the_same_cycle() -> None:
    core, vehicle, _ = speed_hold()
    vehicle.pc104_faults = Pc104Faults(command_timeout=True)
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR
    assert_safe(out)
    raised = events(out, "fault_raised")
    assert [n["fault"] for n in raised] == ["pc104:faults"]
    assert "command_timeout" in raised[0]["detail"]


def test_other_pc104_faults_are_faults_before_engagement_too() -> None:
    core, vehicle = bench()
    vehicle.pc104_faults = Pc104Faults(command_timeout=True, hydraulic=True)
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR
    detail = events(out, "fault_raised")[0]["detail"]
    assert "hydraulic" in detail and "command_timeout" not in detail
