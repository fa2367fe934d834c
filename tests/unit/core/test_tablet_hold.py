"""The tablet's hold-to-move button in the control core: the panel's ENGAGE, no more.

A press engages and lets the source set the speed; held, the vehicle moves; released or
lapsed (its beats stopped), the mode machine's hold-to-move stops it; everything the
panel cannot do, the tablet cannot either.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.core.autopilot import AutopilotWish, Observation
from appliance.core.core import ControlCore
from appliance.core.inputs import TabletHold
from appliance.modes import Mode
from drivers.actuators.messages import Buttons
from tests.unit.core.test_core import HOLD_TO_MOVE, SIM_CALIBRATION
from tests.unit.core.vehicle import BenchVehicle

TIMEOUT_S = 0.3
DT_S = 0.02
WANTED_MPS = 1.0


class OwnSpeed:
    """A source that drives at its own speed (the pallet source does)."""

    name = "own_speed"

    def reset(self) -> None:
        pass

    def update(self, observation: Observation) -> AutopilotWish:
        return AutopilotWish(ready=True, speed_mps=WANTED_MPS)


def _bench() -> tuple[ControlCore, BenchVehicle]:
    core = ControlCore(HOLD_TO_MOVE, SIM_CALIBRATION, autopilot=OwnSpeed())
    vehicle = BenchVehicle()
    for _ in range(50):
        vehicle.step(core, DT_S)
    assert vehicle.last is not None and vehicle.last.mode is Mode.READY
    return core, vehicle


def _beat(vehicle: BenchVehicle, held: bool = True) -> None:
    vehicle.tablet = TabletHold(held, vehicle.now_s + TIMEOUT_S)


def _hold_for(core: ControlCore, vehicle: BenchVehicle, seconds: float) -> None:
    for _ in range(round(seconds / DT_S)):
        _beat(vehicle)  # a beat every cycle: faster than the page's, same meaning
        vehicle.step(core, DT_S)


def test_a_held_tablet_engages_moves_and_a_release_stops_at_once() -> None:
    core, vehicle = _bench()
    _hold_for(core, vehicle, 4.0)
    assert vehicle.last is not None and vehicle.last.mode is Mode.SPEED_HOLD
    assert vehicle.speed_mps > 0.8 * WANTED_MPS
    commanded = vehicle.last.pc104.speed_mps
    _beat(vehicle, held=False)
    out = vehicle.step(core, DT_S)
    assert out.pc104.speed_mps < commanded  # the very next cycle slows down
    vehicle.run(core, 3.0, DT_S)
    assert vehicle.speed_mps < 1e-3


def test_a_page_that_goes_silent_stops_the_vehicle_once_its_last_beat_runs_out() -> None:
    core, vehicle = _bench()
    _hold_for(core, vehicle, 4.0)
    assert vehicle.last is not None
    last_beat_until = vehicle.tablet.until_s if vehicle.tablet else 0.0
    speeds = []
    while vehicle.now_s < last_beat_until + 0.2:
        speeds.append((vehicle.now_s, vehicle.step(core, DT_S).pc104.speed_mps))
    moving = [s for t, s in speeds if t <= last_beat_until]
    slowing = [s for t, s in speeds if t > last_beat_until + DT_S]
    assert min(moving) >= 0.9 * WANTED_MPS  # held while its time lasts
    assert slowing[-1] < slowing[0] < WANTED_MPS  # stopping from the first cycle after


def test_the_tablet_cannot_engage_what_the_panel_could_not() -> None:
    core, vehicle = _bench()
    vehicle.brake_pedal(60.0)  # the operator's foot on the brake: overriding
    _hold_for(core, vehicle, 1.0)
    assert vehicle.last is not None and vehicle.last.mode is Mode.READY
    assert vehicle.speed_mps == 0.0
    vehicle.brake_pedal(0.0)
    vehicle.estop(True)
    _hold_for(core, vehicle, 1.0)
    assert vehicle.last.mode is Mode.ESTOP and vehicle.speed_mps == 0.0


def test_the_operator_override_wins_over_a_held_tablet() -> None:
    core, vehicle = _bench()
    _hold_for(core, vehicle, 3.0)
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    _beat(vehicle)
    out = vehicle.step(core, DT_S)
    assert out.mode not in (Mode.ENGAGED, Mode.SPEED_HOLD)
    _hold_for(core, vehicle, 2.0)  # still held: no engaging again by itself
    assert vehicle.last is not None and vehicle.last.mode not in (Mode.SPEED_HOLD,)


@settings(max_examples=40, deadline=None)
@given(
    beats=st.lists(
        st.tuples(st.booleans(), st.floats(-0.5, 1.0), st.integers(1, 30)), min_size=1, max_size=12
    )
)
def test_the_vehicle_is_driven_only_while_a_beat_holds(
    beats: list[tuple[bool, float, int]],
) -> None:
    """Whatever the tablet says and whenever: the speed asked of the PC104 rises only in
    cycles where the last word was 'held' and its time has not run out."""
    core, vehicle = _bench()
    previous = 0.0
    for held, lasting_s, cycles in beats:
        vehicle.tablet = TabletHold(held, vehicle.now_s + lasting_s)
        for _ in range(cycles):
            out = vehicle.step(core, DT_S)
            holding = held and vehicle.now_s <= vehicle.tablet.until_s
            if out.pc104.speed_mps > previous + 1e-9:
                assert holding
            previous = out.pc104.speed_mps
