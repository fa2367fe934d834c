"""The built-in simulated vehicle: one world and the twins of every device.

The same assembly serves two uses. ``dbw run --config sim`` runs it inside the daemon
(the PC104 twin on python-can's in-process ``virtual`` bus, so no kernel support is
needed); ``dbw sim`` runs it on its own, as separate endpoints a daemon on another
process connects to exactly as to hardware: LMS111s on TCP ports, the PC104 on a
SocketCAN interface (vcan), the actuator boards and (with ``devices.gnss.port =
"sim://gnss"``) the GNSS/INS receiver on pseudo-terminals.
"""

from __future__ import annotations

import asyncio
import math
import os
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

import can as can_lib

from appliance.config import VehicleConfig
from appliance.config.models import CanEndpoint, ColaDialect, Positioning, VehicleKind
from appliance.sim.scanner_errors import draw_scanner_errors, noise_seed
from appliance.sim.site_file import load_site
from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.twins.gnss import GnssTwin, GnssTwinParams
from appliance.sim.twins.lms111 import Lms111Twin
from appliance.sim.twins.pc104 import Pc104Twin
from appliance.sim.twins.pc104_core import TwinParams
from appliance.sim.twins.pc104_pose_loop import PoseLoopParams
from appliance.sim.vehicle import VehicleParams, VehicleState
from appliance.sim.world import SimWorld
from appliance.supervisor import ServiceSpec, beating_service
from drivers.geometry import Pose2D
from drivers.lms111 import Dialect
from drivers.lms111.mounted import mount_pose
from drivers.pc104 import protocol
from drivers.pc104.endpoint import CanInterface
from drivers.pc104.link import BusFactory, bus_factory
from drivers.pc104.slcan import SlcanAdapterBus
from drivers.ptylink import SIM_PORT_PREFIX
from safety.watchdog import RestartPolicy

TWIN_HEARTBEAT_DEADLINE_S = 1.0
GNSS_SIM_PORT = f"{SIM_PORT_PREFIX}gnss"
GNSS_TWIN_SEED = 0  # the receiver's noise: one stream for every run, like a bench recording


@dataclass
class Simulator:
    world: SimWorld
    scanner_twins: dict[str, Lms111Twin] = field(default_factory=dict)
    pc104_twin: Pc104Twin | None = None
    board_twins: ActuatorTwins | None = None
    gnss_twin: GnssTwin | None = None
    services: list[ServiceSpec] = field(default_factory=list)

    def port_path(self, port: str) -> str:
        """``sim://NAME`` -> the tty path of that twin (a board, or ``sim://gnss``)."""
        if port == GNSS_SIM_PORT and self.gnss_twin is not None:
            return self.gnss_twin.port_path
        if self.board_twins is None:
            raise ValueError(f"no simulated device for port {port!r}")
        return self.board_twins.port_path(port)

    def close(self) -> None:
        if self.gnss_twin is not None:  # its link lives in the boards' directory
            self.gnss_twin.close()
        if self.board_twins is not None:
            self.board_twins.close()


def lms111_dialect(dialect: ColaDialect) -> Dialect:
    """The config's name for the encoding, as the LMS111 core spells it."""
    return Dialect.COLA_B if dialect is ColaDialect.COLA_B else Dialect.COLA_A


def twin_service(
    name: str, run: Callable[[Callable[[], None]], Awaitable[None]], policy: RestartPolicy
) -> ServiceSpec:
    return beating_service(name, run, policy, TWIN_HEARTBEAT_DEADLINE_S)


def pc104_twin_params(config: VehicleConfig) -> TwinParams:
    """The PC104 knows its own vehicle: the wheelbase its rear steering turns about, and
    the front end whose centre its oblique pattern steers onto the expected axis; and it
    times out our commands after the vehicle's `safety.lower_layer_command_timeout_s`, as
    the boards' twins do."""
    docking = config.docking
    loop = PoseLoopParams(
        wheelbase_m=config.geometry.wheelbase_m,
        control_point_forward_m=docking.front_end_forward_m or config.geometry.length_m / 2.0,
        max_rear_steer_rad=math.radians(config.limits.max_steer_angle_deg),
        max_crab_rad=math.radians(min(15.0, config.limits.max_steer_angle_deg)),
    )
    return TwinParams(pose_loop=loop, command_max_age_s=config.safety.lower_layer_command_timeout_s)


def build_simulator(
    config: VehicleConfig,
    policy: RestartPolicy,
    *,
    can: CanEndpoint | None = None,
    pty_directory: str | None = None,
) -> Simulator:
    """Every twin of ``config``'s devices around one world; ``can=None`` leaves out the PC104."""
    sim = config.simulation
    world = SimWorld(
        VehicleParams.from_config(config),
        initial=VehicleState(
            x_m=sim.start_x_m, y_m=sim.start_y_m, yaw_rad=math.radians(sim.start_yaw_deg)
        ),
        step_hz=sim.world_step_hz,
        steered_axle="rear" if config.kind is VehicleKind.FORKLIFT else "front",
    )
    simulator = Simulator(world)

    async def run_world(beat: Callable[[], None]) -> None:
        await world.run_realtime(on_step=beat)

    simulator.services.append(twin_service("sim.world", run_world, policy))

    if can is not None:
        if can.interface is CanInterface.SLCAN:
            # The twin plays the USB-CAN adapter too: the daemon opens ``can.channel``.
            adapter_path = can.channel

            def open_adapter() -> can_lib.BusABC:
                return SlcanAdapterBus(adapter_path)

            open_bus: BusFactory = open_adapter
        else:
            open_bus = bus_factory(can, protocol.HL_IDS)  # what a PC104 listens to
        pc104 = Pc104Twin(open_bus, world, params=pc104_twin_params(config), step_world=False)
        simulator.pc104_twin = pc104

        async def run_pc104(beat: Callable[[], None]) -> None:
            await _beating_while(pc104.run(), beat)

        simulator.services.append(twin_service("sim.pc104", run_pc104, policy))

    site = load_site(sim.site)

    def platform_pose(_t_s: float) -> Pose2D:
        state = world.state
        return Pose2D(state.x_m, state.y_m, state.platform_yaw_rad)

    sides = (
        ("left", config.devices.lms111_left, config.geometry.scanner_left_mount),
        ("right", config.devices.lms111_right, config.geometry.scanner_right_mount),
    )
    realistic = sim.scanner_model == "realistic"
    for index, (side, endpoint, mount) in enumerate(sides):
        # The twin scans from its true mount (``twin.true_mount``): the configured one
        # composed with the drawn mount error, which the daemon does not know.
        twin = Lms111Twin(
            site,
            mount_pose(mount),
            platform_pose,
            name=f"sim.lms111_{side}",
            serial_number=0x0142_0001 + index,
            errors=draw_scanner_errors(sim.scanner_seed, index, realistic=realistic),
            seed=noise_seed(sim.scanner_seed, index),
            host=endpoint.host,
            port=endpoint.port,
            scan_frequency_hz=endpoint.scan_frequency_hz,
            angular_resolution_deg=endpoint.angular_resolution_deg,
            dialect=lms111_dialect(endpoint.cola_dialect),
        )
        simulator.scanner_twins[side] = twin
        simulator.services.append(twin_service(f"sim.lms111_{side}", twin.run, policy))

    if pty_directory is not None:
        os.makedirs(pty_directory, exist_ok=True)
    boards = ActuatorTwins.from_config(config, world, directory=pty_directory)
    simulator.board_twins = boards

    async def run_boards(beat: Callable[[], None]) -> None:
        await boards.run(on_step=beat)

    simulator.services.append(twin_service("sim.boards", run_boards, policy))
    gnss = config.devices.gnss
    if gnss is not None and gnss.port == GNSS_SIM_PORT:
        _add_gnss_twin(
            simulator, config.positioning, boards.directory, policy, config.simulation.gnss_sigma_m
        )
    return simulator


def antenna_truth(
    state: VehicleState, positioning: Positioning
) -> tuple[float, float, float, float]:
    """(east_m, north_m, yaw_rad, speed_mps) of the antenna: the centre moved by the
    configured lever arm, turned with the chassis. A receiver reports where its antenna
    is, and the route source takes the lever arm back off; a twin reporting the centre
    would hide an error in that step."""
    forward_m, left_m = positioning.antenna_forward_m, positioning.antenna_left_m
    cos_yaw, sin_yaw = math.cos(state.yaw_rad), math.sin(state.yaw_rad)
    east_m = state.x_m + forward_m * cos_yaw - left_m * sin_yaw
    north_m = state.y_m + forward_m * sin_yaw + left_m * cos_yaw
    return east_m, north_m, state.yaw_rad, state.speed_mps


def _add_gnss_twin(
    simulator: Simulator,
    positioning: Positioning,
    directory: str,
    policy: RestartPolicy,
    sigma_m: float = 0.05,
) -> None:
    """The receiver at ``directory``/gnss, sampling the world's true pose at its own rate
    (10 Hz, 5 cm noise: `GnssTwinParams`' clean RTK receiver), in the frame of the config's
    origin so that the daemon's local frame and the world's coincide."""
    origin = positioning.origin
    params = GnssTwinParams(position_noise_m=sigma_m)
    if origin is not None:
        params = GnssTwinParams(
            origin_lat_deg=origin.lat_deg,
            origin_lon_deg=origin.lon_deg,
            origin_alt_m=origin.alt_m,
            position_noise_m=sigma_m,
        )
    twin = GnssTwin(os.path.join(directory, "gnss"), params, seed=GNSS_TWIN_SEED)
    simulator.gnss_twin = twin
    world = simulator.world

    def truth(_now_s: float) -> tuple[float, float, float, float]:
        return antenna_truth(world.state, positioning)

    async def run_gnss(beat: Callable[[], None]) -> None:
        await _beating_while(twin.run(truth), beat)

    simulator.services.append(twin_service("sim.gnss", run_gnss, policy))


async def _beating_while(work: Awaitable[None], beat: Callable[[], None]) -> None:
    """Beat every 0.1 s for as long as ``work`` runs (for twins without a beat hook)."""
    async with asyncio.TaskGroup() as group:
        task = group.create_task(_await(work))
        while not task.done():
            beat()
            await asyncio.sleep(0.1)


async def _await(work: Awaitable[None]) -> None:
    await work
