"""Vehicle I/O: the drivers a profile asks for, and the simulated vehicle behind them.

This is the one place that turns the config's ``devices`` into supervised services,
topics and safe-stop targets. With ``simulation.enabled`` it also starts the simulated
world and the twins: by default in a child process (``appliance.sim_process``), with
``simulation.placement = "inline"`` in this one. Either way the clients talk to them over
the transports they use on the vehicle (TCP, a CAN bus, real ptys), so nothing downstream
can tell a twin from the hardware.

Drivers keep beating while they reconnect: whether a *device* is there is a question of
input staleness for the safety layer; the supervisor's heartbeat answers whether the
*software* is alive. The links that actuate (PC104, actuator boards) are critical
services: if their software keeps failing, the daemon latches an error; the scanners
are not, since nothing actuates from them yet, nor is the GNSS/INS receiver (the route
source refuses a lost or degraded fix itself, and a vehicle may carry one only to log).
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field, replace
from typing import Any

from appliance.board_clients import BoardClients, make_board_clients
from appliance.config import VehicleConfig, parts
from appliance.config.models import SimPlacement
from appliance.core.core import CoreOutput
from appliance.core.inputs import LinkCounts
from appliance.core.output import printable
from appliance.gnss_input import GnssInput
from appliance.logs import get_logger
from appliance.modes import Mode
from appliance.sim_process import SimProcess
from appliance.simulator import Simulator, build_simulator, lms111_dialect
from appliance.supervisor import PermanentServiceError, ServiceSpec, beating_service
from appliance.timing import ControlSlot
from appliance.topics import TopicRegistry
from drivers.actuators.client import ActuatorClient
from drivers.actuators.messages import (
    MAX_DISPLAY_CHARS,
    BrakeCommand,
    PanelCommand,
    SteeringCommand,
    SteeringMode,
    ThrottleCommand,
)
from drivers.lms111.client import Lms111Client
from drivers.lms111.mounted import MountedScan
from drivers.lms111.session import Lms111ConfigError
from drivers.pc104.client import Pc104Client
from drivers.pc104.endpoint import CanInterface
from drivers.pc104.messages import MotionCommand, MotionPattern
from drivers.ptylink import SIM_PORT_PREFIX
from drivers.topics import Topic
from safety.safe_stop import SafeCommand, SafeStopTarget
from safety.watchdog import RestartPolicy

log = get_logger("vehicle_io")

DRIVER_HEARTBEAT_DEADLINE_S = 1.0
# Work that starts this close to a control deadline waits for that cycle (ControlSlot):
# a CoLa-A scan's decoding, the longest such work today, is 0.55 ms median and 0.7 ms p99
# (benchmarks/bench_lms111_decode.py, 1,081 points with RSSI), with room for a slow turn;
# a PC104 burst (three status frames through cantools) is about 0.5 ms.
BULK_WORK_BUDGET_S = 0.0015


@dataclass
class VehicleIO:
    """Everything the daemon runs to talk to (or simulate) the vehicle."""

    topics: TopicRegistry = field(default_factory=TopicRegistry)
    services: list[ServiceSpec] = field(default_factory=list)
    safe_stop_targets: list[SafeStopTarget] = field(default_factory=list)
    simulator: Simulator | None = None  # an inline simulation (its twins, reachable)
    sim_process: SimProcess | None = None  # the simulation in its own process
    boards: BoardClients | None = None
    pc104: Pc104Client | None = None
    scanners: dict[str, Lms111Client] = field(default_factory=dict)
    gnss: GnssInput | None = None
    # Deferrable work waits here for the control cycle due (the daemon attaches its ticker).
    work_slot: ControlSlot = field(default_factory=lambda: ControlSlot(BULK_WORK_BUDGET_S))
    _closers: list[Callable[[], None]] = field(default_factory=list)

    def raw_sources(self) -> list[tuple[str, str, list[Any]]]:
        """Every link's raw input as ``(name, kind, listeners)``: kind "bytes" (a chunk
        and its receive time) or "can" (a python-can message and its receive time). The
        recorder adds itself to each list."""
        sources: list[tuple[str, str, list[Any]]] = [
            (f"lms111.{side}", "bytes", client.raw_listeners)
            for side, client in self.scanners.items()
        ]
        if self.boards is not None:
            sources += [
                (f"board.{client.board.value}", "bytes", client.raw_listeners)
                for client in self.boards.all()
            ]
        if self.pc104 is not None:
            sources.append(("can", "can", self.pc104.raw_listeners))
        if self.gnss is not None:
            sources.append(("gnss", "bytes", self.gnss.client.raw_listeners))
        return sources

    def close(self) -> None:
        """Release what outlives tasks (pty pairs, temporary directories)."""
        for closer in reversed(self._closers):
            try:
                closer()
            except Exception as exc:  # cleanup must go on
                log.warning("close_failed", error=f"{type(exc).__name__}: {exc}")
        self._closers.clear()


class BoardsSafeStop:
    """Throttle to 0, brake to the safe level, steering clutch out: one frame each."""

    name = "actuator_boards"

    def __init__(self, boards: BoardClients) -> None:
        self._boards = boards

    def command_safe_state(self, command: SafeCommand, reason: str) -> None:
        boards = self._boards
        orders: list[tuple[ActuatorClient[Any], object]] = [
            (boards.throttle, ThrottleCommand(enable=False)),
            (boards.brake, BrakeCommand(enable=True, position_pct=command.brake_pct)),
            (boards.steering, SteeringCommand(SteeringMode.RELEASE)),
        ]
        failures = []
        for client, order in orders:
            try:
                client.set_command(order)  # type: ignore[arg-type]
            except Exception as exc:  # tell the other boards anyway
                failures.append(f"{type(exc).__name__}: {exc}")
        if failures:
            raise RuntimeError("; ".join(failures))


def _service(
    name: str,
    run: Callable[[Callable[[], None]], Awaitable[None]],
    policy: RestartPolicy,
    deadline_s: float,
    *,
    critical: bool = False,
) -> ServiceSpec:
    # A device may take a while to answer at start-up; the client beats while it waits.
    return beating_service(
        name, run, policy, deadline_s, critical=critical, startup_grace_s=max(deadline_s, 5.0)
    )


def build_vehicle_io(config: VehicleConfig, policy: RestartPolicy) -> VehicleIO:
    io = VehicleIO()
    resolve: Callable[[str], str] | None = None
    if config.simulation.enabled and config.simulation.placement is SimPlacement.PROCESS:
        sim_process = SimProcess(config)
        io.sim_process = sim_process
        io._closers.append(sim_process.close)
        # Not critical: if the simulation dies, its inputs go stale and the safety layer
        # holds the vehicle; the supervisor starts a new one.
        io.services.append(
            beating_service(
                "sim",
                sim_process.run,
                policy,
                DRIVER_HEARTBEAT_DEADLINE_S,
                startup_grace_s=sim_process.ready_timeout_s,
            )
        )
        # The drivers reach the child as hardware: its SLCAN adapter, its ptys.
        if sim_process.can_endpoint is not None:
            devices = config.devices.model_copy(update={"can": sim_process.can_endpoint})
            config = config.model_copy(update={"devices": devices})
        resolve = sim_process.port_path
    elif config.simulation.enabled:
        if uses_pc104(config) and config.devices.can.interface is not CanInterface.VIRTUAL:
            raise ValueError(
                "an inline simulated vehicle runs its PC104 twin in this process, on "
                "python-can's virtual bus: set devices.can.interface = 'virtual' (or "
                "simulation.placement = 'process')"
            )
        simulator = build_simulator(
            config, policy, can=config.devices.can if uses_pc104(config) else None
        )
        io.simulator = simulator
        io.services.extend(simulator.services)
        io._closers.append(simulator.close)
        resolve = simulator.port_path
    if uses_pc104(config):
        _build_pc104(config, io, policy)
    _build_scanners(config, io, policy)
    _build_boards(config, io, policy, resolve)
    _build_gnss(config, io, policy, resolve)
    return io


def uses_pc104(config: VehicleConfig) -> bool:
    """Whether this vehicle has a PC104 to talk to: a ``pedals`` vehicle (the Husky) has
    none, and a client waiting for a controller that is not there would be a critical
    link that never comes up."""
    return config.speed_path == "pc104"


class Pc104SafeStop:
    """STOP to the PC104: its own PID brings the vehicle to rest and holds it."""

    name = "pc104"

    def __init__(self, client: Pc104Client) -> None:
        self._client = client

    def command_safe_state(self, command: SafeCommand, reason: str) -> None:
        self._client.send_command(MotionCommand(MotionPattern.STOP, 0.0, 0.0, 0.0, False))
        self._client.send_pose(None, None)


def _build_pc104(config: VehicleConfig, io: VehicleIO, policy: RestartPolicy) -> None:
    """The PC104 link (critical: it is how the vehicle's own controller hears us)."""
    client = Pc104Client(parts.pc104_client_params(config), config.devices.can)
    client.before_decode = io.work_slot.clear
    io.pc104 = client
    for topic in (
        client.topics.status,
        client.topics.wheel_angles,
        client.topics.motor_pulses,
        client.topics.inclinometer,
        client.topics.heartbeat,
    ):
        io.topics.register(topic.name, topic)
    io.services.append(
        _service("pc104", client.run, policy, DRIVER_HEARTBEAT_DEADLINE_S, critical=True)
    )
    io.safe_stop_targets.append(Pc104SafeStop(client))


def _build_scanners(config: VehicleConfig, io: VehicleIO, policy: RestartPolicy) -> None:
    """Both LMS111 clients (and, in simulation, the twins they connect to)."""
    sides = (
        ("left", config.devices.lms111_left, config.geometry.scanner_left_mount),
        ("right", config.devices.lms111_right, config.geometry.scanner_right_mount),
    )
    for side, endpoint, mount in sides:
        name = f"lms111_{side}"
        topic: Topic[MountedScan] = Topic(f"scan.{side}")
        io.topics.register(topic.name, topic)
        client = Lms111Client(
            name,
            endpoint,
            mount,
            topic,
            dialect=lms111_dialect(endpoint.cola_dialect),
            read_deadline_periods=5,
            beat_while_waiting=True,
            before_decode=io.work_slot.clear,
            backoff_cap_s=parts.reconnect_cap_s(config),
        )
        io.scanners[side] = client
        io.services.append(
            _service(
                name, _permanent_on_config_error(client.run), policy, DRIVER_HEARTBEAT_DEADLINE_S
            )
        )


def _permanent_on_config_error(
    run: Callable[[Callable[[], None]], Awaitable[None]],
) -> Callable[[Callable[[], None]], Awaitable[None]]:
    """A scanner that refuses its configuration or login will refuse it again: give up."""

    async def wrapped(beat: Callable[[], None]) -> None:
        try:
            await run(beat)
        except Lms111ConfigError as exc:
            raise PermanentServiceError(str(exc)) from exc

    return wrapped


def _build_boards(
    config: VehicleConfig,
    io: VehicleIO,
    policy: RestartPolicy,
    resolve: Callable[[str], str] | None,
) -> None:
    boards = make_board_clients(
        config, resolve, beat_while_reconnecting=True, backoff_cap_s=parts.reconnect_cap_s(config)
    )
    io.boards = boards
    for name, client in (
        ("steering", boards.steering),
        ("throttle", boards.throttle),
        ("brake", boards.brake),
        ("panel", boards.panel),
    ):
        io.topics.register(f"board.{name}", client.telemetry)
        io.services.append(
            _service(
                f"board.{name}", client.run, policy, DRIVER_HEARTBEAT_DEADLINE_S, critical=True
            )
        )
    io.safe_stop_targets.append(BoardsSafeStop(boards))


def _build_gnss(
    config: VehicleConfig,
    io: VehicleIO,
    policy: RestartPolicy,
    resolve: Callable[[str], str] | None,
) -> None:
    """The GNSS/INS receiver, when the vehicle has one. Not critical: a lost fix is the
    route source's to refuse (the core then faults and stops); a vehicle that only logs
    its track must not stop for it. A crash is still restarted with the shared policy."""
    endpoint = config.devices.gnss
    if endpoint is None:
        return
    port = endpoint.port
    if port.startswith(SIM_PORT_PREFIX):
        if resolve is None:
            raise ValueError(
                f"devices.gnss.port is {port!r}, a simulated receiver, but simulation.enabled "
                "is false: set the real serial device or enable the simulation"
            )
        port = resolve(port)
    gnss = GnssInput(
        endpoint,
        config.positioning.origin,
        port,
        max_age_s=config.positioning.max_fix_age_s,
        backoff_cap_s=parts.reconnect_cap_s(config),
    )
    io.gnss = gnss
    io.topics.register(gnss.topic.name, gnss.topic)
    io.services.append(_service("gnss", gnss.run, policy, DRIVER_HEARTBEAT_DEADLINE_S))


def link_summary(io: VehicleIO) -> dict[str, str]:
    """One short line per device link for the periodic ``heartbeats`` log."""
    links: dict[str, str] = {}
    if io.pc104 is not None:
        h = io.pc104.health()
        source = h.control_source.name.lower() if h.control_source is not None else "?"
        links["pc104"] = (
            f"{'up' if h.connected else 'DOWN'}{' STALE' if h.stale else ''} "
            f"{h.frames_in_per_s:.0f}/{h.frames_out_per_s:.0f} fps in/out, control={source}, "
            f"crc={h.crc_errors} counter={h.counter_errors} malformed={h.malformed_frames} "
            f"drops={h.send_drops} bus={h.bus_condition.name.lower()}"
        )
    for side, scanner in io.scanners.items():
        s = scanner.health
        links[f"lms111_{side}"] = (
            f"{s.state} {s.scans_per_s:.1f} scans/s, dropped={s.dropped_scans} "
            f"malformed={s.malformed_telegrams} reconnects={s.reconnects}"
        )
    if io.boards is not None:
        for name, client in (
            ("steering", io.boards.steering),
            ("throttle", io.boards.throttle),
            ("brake", io.boards.brake),
            ("panel", io.boards.panel),
        ):
            b = client.health()
            links[f"board.{name}"] = (
                f"{'up' if b.connected else 'DOWN'}{' STALE' if b.stale else ''} "
                f"{b.frames_per_s:.0f} fps, crc={b.crc_errors} reconnects={b.reconnects} "
                f"lease_expired={b.lease_expiries}"
            )
    if io.gnss is not None:
        links["gnss"] = io.gnss.link_line()
    return links


def input_ages_s(io: VehicleIO, now_s: float) -> dict[str, float]:
    """Age of every input topic, rounded for logs (inf: never received)."""
    return {
        name: (round(age, 3) if math.isfinite(age) else age)
        for name, age in io.topics.ages_s(now_s).items()
    }


class VehicleCommandSink:
    """Sends one cycle's commands to the boards (leased) and the PC104.

    Every path is told, even if an earlier one raised; the first error is re-raised
    afterwards so the control service fails (and the supervisor's safe stop runs) instead
    of carrying on with one actuator path silently out of date.
    """

    def __init__(
        self, io: VehicleIO, lease_s: float, display_note: Callable[[], str] | None = None
    ) -> None:
        self._io = io
        self._lease_s = lease_s
        # What the daemon adds to the panel's text outside an error (the tablet's pairing
        # code): shown at the vehicle, to whoever stands at it, and nowhere else.
        self._display_note = display_note

    def _panel(self, output: CoreOutput) -> PanelCommand:
        note = self._display_note() if self._display_note is not None else ""
        if not note or output.mode in (Mode.ERROR, Mode.ESTOP):
            return output.panel
        room = max(0, MAX_DISPLAY_CHARS - len(note) - 1)
        text = f"{output.panel.display_text[:room]} {note}".strip()
        return replace(output.panel, display_text=printable(text)[:MAX_DISPLAY_CHARS])

    def send(self, output: CoreOutput) -> None:
        errors: list[Exception] = []
        boards = self._io.boards
        if boards is not None:
            orders: list[tuple[ActuatorClient[Any], Any]] = [
                (boards.steering, output.steering),
                (boards.throttle, output.throttle),
                (boards.brake, output.brake),
                (boards.panel, self._panel(output)),
            ]
            for client, command in orders:
                try:
                    client.set_command(command, lease_s=self._lease_s)
                except Exception as exc:
                    errors.append(exc)
        pc104 = self._io.pc104
        if pc104 is not None:
            try:
                pc104.send_command(output.pc104, output.now_s)
                pc104.send_pose(output.pc104_pose, output.pc104_expected_pose, output.now_s)
                pc104.set_state(output.hl_state)
            except Exception as exc:
                errors.append(exc)
        if errors:
            raise errors[0]


def pc104_link_counts(io: VehicleIO) -> LinkCounts:
    """The PC104 link's error and frame totals, for the safety layer's error budget."""
    if io.pc104 is None:
        return LinkCounts()
    h = io.pc104.health()
    errors = h.crc_errors + h.counter_errors + h.malformed_frames
    return LinkCounts(errors=errors, good=max(h.frames_received - errors, 0))
