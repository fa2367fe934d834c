"""The ``pedals`` speed path against the throttle and brake twins, in real time.

The control core runs its 50 Hz cycle against the four board twins and the simulated
world over real pseudo-terminals and the real board clients, as the daemon wires them,
with no PC104 anywhere: the world's plant is moved by the throttle and brake boards alone.
What the daemon and the simulator do not wire yet is built here, and said so: the GNSS/INS
epoch is made each cycle from the world's true speed (50 ms old) and the two scanners are
declared fresh (they are not what is under test). Everything else the core sees is what
the boards say.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import pytest

from appliance.board_clients import BoardClients, make_board_clients
from appliance.config import load_config
from appliance.config.calibration_file import BUILTIN_SIMULATED, load_calibration
from appliance.config.models import VehicleConfig
from appliance.core.core import ControlCore
from appliance.core.inputs import ControlInputs
from appliance.core.output import CoreOutput
from appliance.localization.gnss_pose import GnssPose, HeadingSource, SigmaSource
from appliance.modes import Mode
from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.actuators.client import ActuatorClient
from drivers.actuators.messages import BoardStatus, Buttons
from drivers.gnss.sentences import FixQuality


def pedals_config() -> VehicleConfig:
    """The sim profile on the pedals path, with a throttle limit low enough to bind: the
    plant needs 0.05 /s x v / (0.01 m/s² per %) = 5 % to hold 1 m/s, 10 % for 2 m/s."""
    data = load_config("sim").model_dump(exclude_unset=True)
    data["speed_path"] = "pedals"
    data["limits"] = data.get("limits", {}) | {"throttle_max_pct": 8.0}
    return VehicleConfig.model_validate(data)


CONFIG = pedals_config()
CALIBRATION = load_calibration(BUILTIN_SIMULATED, CONFIG.name, simulation_enabled=True)
LIMITS = CONFIG.limits
PERIOD_S = 1.0 / CONFIG.rates.control_hz
LEASE_S = 3 * PERIOD_S
GNSS_LATENCY_S = 0.05
TOL = 1e-9


@dataclass
class Cycle:
    now_s: float
    out: CoreOutput
    speed_mps: float
    throttle_actuator_pct: float
    world_throttle_pct: float
    world_brake_pct: float


@dataclass
class Rig:
    world: SimWorld
    twins: ActuatorTwins
    clients: BoardClients
    core: ControlCore
    cycles: list[Cycle] = field(default_factory=list)

    @property
    def last(self) -> Cycle:
        return self.cycles[-1]

    def inputs(self, now_s: float) -> ControlInputs:
        c = self.clients
        ages: dict[str, float] = {"scan.left": 0.0, "scan.right": 0.0}
        for name, client in (
            ("board.steering", c.steering),
            ("board.throttle", c.throttle),
            ("board.brake", c.brake),
            ("board.panel", c.panel),
        ):
            ages[name] = client.telemetry.age_s(now_s)
        ages["steering.pot"] = ages["board.steering"]
        panel = c.panel.telemetry.latest()
        state = self.world.state
        # Speed over ground is unsigned; the course says which way (the world's is signed).
        course = state.yaw_rad if state.speed_mps >= 0.0 else state.yaw_rad + math.pi
        gnss = GnssPose(
            measurement_time_s=now_s - GNSS_LATENCY_S,
            utc_time_of_day_s=now_s % 86400.0,
            east_m=state.x_m,
            north_m=state.y_m,
            up_m=0.0,
            quality=FixQuality.RTK_FIXED,
            satellites=12,
            hdop=0.8,
            yaw_rad=state.yaw_rad,
            heading_source=HeadingSource.TRUE_HEADING,
            course_yaw_rad=course,
            speed_mps=abs(state.speed_mps),
            yaw_rate_rad_per_s=0.0,
            sigma_east_m=0.02,
            sigma_north_m=0.02,
            sigma_worst_m=0.02,
            sigma_source=SigmaSource.GST,
        )
        return ControlInputs(
            ages_s=ages,
            steering=latest(c.steering),
            throttle=latest(c.throttle),
            brake=latest(c.brake),
            panel=None if panel is None else panel.value,
            panel_seq=None if panel is None else panel.seq,
            gnss=gnss,
        )

    def cycle(self) -> None:
        now_s = time.monotonic()
        out = self.core.step(self.inputs(now_s), now_s)
        c = self.clients
        c.steering.set_command(out.steering, lease_s=LEASE_S)
        c.throttle.set_command(out.throttle, lease_s=LEASE_S)
        c.brake.set_command(out.brake, lease_s=LEASE_S)
        c.panel.set_command(out.panel, lease_s=LEASE_S)
        command = self.world.command
        self.cycles.append(
            Cycle(
                now_s,
                out,
                self.world.state.speed_mps,
                self.twins.throttle.actuator_position_pct,
                command.throttle_pct,
                command.brake_pct,
            )
        )

    async def run(self) -> None:
        next_s = time.monotonic()
        while True:
            self.cycle()
            next_s += PERIOD_S
            await asyncio.sleep(max(0.0, next_s - time.monotonic()))


def operator_throttle(rig: Rig, pct: float) -> None:
    """The operator's foot on the throttle pedal: the twin reports it and the world feels
    the larger of the pedal and the actuator, as on the shared linkage."""
    rig.twins.throttle.operator_pedal(pct)


def latest(client: ActuatorClient[Any]) -> Any:
    sample = client.telemetry.latest()
    return None if sample is None else sample.value


async def wait_until(predicate: Callable[[], bool], timeout_s: float) -> float:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.002)
    return time.monotonic()


@pytest.fixture
async def rig() -> AsyncIterator[Rig]:
    world = SimWorld(VehicleParams.from_config(CONFIG))
    twins = ActuatorTwins.from_config(CONFIG, world)
    clients = make_board_clients(CONFIG, twins.port_path)
    rig = Rig(world, twins, clients, ControlCore(CONFIG, CALIBRATION))
    tasks = [asyncio.create_task(twins.run()), asyncio.create_task(world.run_realtime())]
    tasks += [asyncio.create_task(c.run(lambda: None)) for c in clients.all()]
    try:
        await wait_until(lambda: all(c.health().healthy for c in clients.all()), 3.0)
        tasks.append(asyncio.create_task(rig.run()))
        await wait_until(lambda: bool(rig.cycles) and rig.last.out.mode is Mode.READY, 2.0)
        yield rig
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        twins.close()


async def test_speed_hold_on_the_throttle_twin_and_a_brake_tap_hands_back(rig: Rig) -> None:
    twins = rig.twins
    # READY and ENGAGED: our pedals released; the operator's foot drives.
    twins.panel.press(Buttons.ENGAGE)
    await wait_until(lambda: rig.last.out.mode is Mode.ENGAGED, 1.0)
    operator_throttle(rig, 60.0)
    await wait_until(lambda: rig.world.state.speed_mps >= 1.0, 6.0)
    twins.panel.press(Buttons.SPEED_PLUS)
    await wait_until(lambda: rig.last.out.mode is Mode.SPEED_HOLD, 1.0)
    set_mps = rig.core.state.set_speed_mps
    assert set_mps is not None and 0.9 <= set_mps <= 1.3
    before_hold = len(rig.cycles)
    operator_throttle(rig, 0.0)
    await asyncio.sleep(5.0)
    late = [c.speed_mps for c in rig.cycles if c.now_s >= rig.last.now_s - 2.0]
    assert max(abs(v - set_mps) for v in late) < 0.1  # held on the throttle
    # Four + presses ask for 1 m/s more than the throttle limit can give.
    for _ in range(4):
        twins.panel.press(Buttons.SPEED_PLUS)
        await asyncio.sleep(0.06)
    assert rig.core.state.set_speed_mps == pytest.approx(set_mps + 1.0)
    await asyncio.sleep(3.0)
    held = rig.cycles[before_hold:]

    # Our throttle drives the twin, inside the safety limits, never with the brake.
    throttles = [c.out.throttle.position_pct if c.out.throttle.enable else 0.0 for c in held]
    brakes = [c.out.brake.position_pct if c.out.brake.enable else 0.0 for c in held]
    assert LIMITS.throttle_max_pct - 0.5 <= max(throttles) <= LIMITS.throttle_max_pct + TOL
    assert max(c.throttle_actuator_pct for c in held) <= LIMITS.throttle_max_pct + 0.01
    assert max(c.world_throttle_pct for c in held) <= LIMITS.throttle_max_pct + 0.01
    assert rig.last.speed_mps < set_mps + 0.5  # still short of the set speed, as it must be
    for a, b, thr, brk in zip(held, held[1:], throttles[1:], brakes[1:], strict=False):
        rise = thr - (a.out.throttle.position_pct if a.out.throttle.enable else 0.0)
        dt_s = min(b.now_s - a.now_s, 0.1)
        assert rise <= LIMITS.max_throttle_rate_pct_per_s * dt_s + 1e-6
        assert thr == 0.0 or brk == 0.0
    assert latest(rig.clients.throttle).status & BoardStatus.ENGAGED

    # A brake tap: speed hold ends in the cycle that sees it, our throttle lets go.
    throttle_before = rig.last.throttle_actuator_pct
    assert throttle_before > 1.0
    tapped = len(rig.cycles)
    twins.brake.operator_brake_tap(40.0, 0.3)
    await wait_until(lambda: rig.last.out.mode is Mode.ENGAGED, 0.5)
    first = next(c for c in rig.cycles[tapped:] if c.out.mode is Mode.ENGAGED)
    assert not first.out.throttle.enable and not first.out.brake.enable
    assert all(c.out.throttle.enable for c in rig.cycles[tapped:] if c.out.mode is Mode.SPEED_HOLD)
    released_s = await wait_until(lambda: twins.throttle.actuator_position_pct < 1.0, 1.0)
    assert released_s - first.now_s < 0.5
    assert rig.core.state.mode is Mode.ENGAGED  # steering stays automatic
