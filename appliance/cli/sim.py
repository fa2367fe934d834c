"""`dbw sim`: the simulated vehicle as separate endpoints, for a daemon in another process.

It starts the world and every twin, prints where each device can be reached, and writes
a vehicle file that points `dbw run` at them: the daemon then runs exactly as on the
vehicle (simulation disabled), over TCP, SocketCAN and real ttys.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
from pathlib import Path

import click
import structlog

from appliance.cli.lazy import LazyGroup
from appliance.config import ConfigError, VehicleConfig, load_config
from appliance.config.atomic import write_text_atomic
from appliance.config.calibration_file import write_calibration
from appliance.config.loader import to_toml
from appliance.config.models import CanEndpoint
from appliance.config.simulated_calibration import servo_of, simulated_calibration
from appliance.logs import get_logger
from appliance.sim.bench import SimBench
from appliance.sim.bench_socket import serve_bench
from appliance.sim.scanner_truth import with_simulated_scanners
from appliance.simulator import Simulator, build_simulator
from appliance.supervisor import Supervisor
from drivers.pc104.endpoint import CanInterface
from safety.watchdog import RestartPolicy

log = get_logger("sim")

BOARDS = ("steering", "throttle", "brake", "panel")


def daemon_config(
    config: VehicleConfig,
    simulator: Simulator,
    can: CanEndpoint | None,
    calibration_file: Path | None = None,
) -> str:
    """A vehicle file for `dbw run` that reaches this simulator's endpoints."""
    data = config.model_dump(mode="json")
    data["name"] = f"{config.name}-via-dbw-sim"
    data["simulation"]["enabled"] = False
    if calibration_file is not None:
        data["paths"]["calibration_file"] = str(calibration_file)
    assert simulator.board_twins is not None
    for board in BOARDS:
        path = simulator.board_twins.port_path(f"sim://{board}")
        data["devices"][f"{board}_serial"]["port"] = path
    if simulator.gnss_twin is not None:
        data["devices"]["gnss"]["port"] = simulator.gnss_twin.port_path
    if can is not None:
        data["devices"]["can"]["interface"] = can.interface.value
        data["devices"]["can"]["channel"] = can.channel
    header = (
        "# Written by `dbw sim`: run `dbw run --config THIS_FILE` in another terminal.\n"
        "# Valid while that `dbw sim` runs (the serial ports are its pseudo-terminals).\n"
    )
    return header + to_toml(data) + "\n"


async def run_simulator(
    config: VehicleConfig,
    can: CanEndpoint | None,
    pty_directory: str | None,
    write_config: Path | None,
    duration_s: float | None,
    *,
    ready_fd: int | None = None,
    exit_on_stdin_eof: bool = False,
    bench_socket: Path | None = None,
) -> int:
    policy = RestartPolicy()
    simulator = build_simulator(config, policy, can=can, pty_directory=pty_directory)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    supervisor = Supervisor(simulator.services)
    root = asyncio.create_task(supervisor.run(), name="simulator")
    bench: asyncio.Server | None = None
    try:
        await asyncio.wait_for(supervisor.wait_critical_up(), 5.0)
        assert simulator.board_twins is not None
        if bench_socket is not None:
            bench = await serve_bench(
                bench_socket,
                SimBench(
                    simulator.world,
                    simulator.board_twins,
                    simulator.pc104_twin,
                    simulator.scanner_twins,
                    gnss=simulator.gnss_twin,
                ),
            )
        left, right = config.devices.lms111_left, config.devices.lms111_right
        endpoints = {
            "lms111_left": f"{left.host}:{left.port}",
            "lms111_right": f"{right.host}:{right.port}",
            "pc104": f"{can.interface.value}:{can.channel}"
            if can
            else "not simulated (no --can-channel or --can-slcan)",
            **{
                f"{board}_serial": simulator.board_twins.port_path(f"sim://{board}")
                for board in BOARDS
            },
            **({"gnss": simulator.gnss_twin.port_path} if simulator.gnss_twin is not None else {}),
            "bench": str(bench_socket) if bench_socket is not None else "none (--bench-socket)",
        }
        if ready_fd is None:  # a daemon that started us reads no endpoint table
            for name, where in endpoints.items():
                click.echo(f"{name:>16}: {where}")
        if write_config is not None:
            # The simulated vehicle's calibration beside the vehicle file: the daemon in
            # the other process has simulation disabled, so it cannot use the built-in one.
            calibration_file = write_config.with_name(write_config.stem + ".calibration.toml")
            await asyncio.to_thread(
                write_calibration,
                calibration_file,
                # A flat-bed's scanners too: the other process cannot know their truth.
                with_simulated_scanners(
                    simulated_calibration(
                        f"{config.name}-via-dbw-sim",
                        servo=servo_of(config.simulation.steering.steering_ratio),
                    ),
                    config,
                ),
            )
            text = daemon_config(config, simulator, can, calibration_file.resolve())
            await asyncio.to_thread(write_text_atomic, write_config, text)
            click.echo(f"{'daemon config':>16}: {write_config}  (dbw run --config {write_config})")
        sys.stdout.flush()
        log.info("simulator_ready", endpoints=endpoints)
        if ready_fd is not None:
            await asyncio.to_thread(_tell_ready, ready_fd)
        if exit_on_stdin_eof:
            _stop_on_stdin_eof(loop, stop)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), duration_s)
        return 0
    finally:
        if bench is not None:
            bench.close()
        root.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.wait_for(root, 2.0)
        simulator.close()


def _tell_ready(fd: int) -> None:
    try:
        os.write(fd, b"ready\n")
    finally:
        os.close(fd)


def _stop_on_stdin_eof(loop: asyncio.AbstractEventLoop, stop: asyncio.Event) -> None:
    """Stop when stdin ends: the daemon that started us is gone, however it went."""
    fd = sys.stdin.fileno()

    def on_readable() -> None:
        try:
            data = os.read(fd, 4096)
        except OSError:
            data = b""
        if not data:
            loop.remove_reader(fd)
            log.info("simulator_parent_gone")
            stop.set()

    loop.add_reader(fd, on_readable)


@click.group(
    cls=LazyGroup,
    lazy_subcommands={
        name: f"appliance.cli.sim_{name}:{name}" for name in ("dock", "pallet", "survey", "track")
    },
    invoke_without_command=True,
)
@click.option("--config", "config_name", metavar="FILE|PROFILE", default="sim", show_default=True)
@click.option(
    "--can-channel",
    default=None,
    help="SocketCAN interface for the PC104 twin (e.g. vcan0).",
)
@click.option(
    "--can-slcan",
    "can_slcan",
    metavar="PATH",
    default=None,
    help="Put the PC104 twin behind a simulated SLCAN USB-CAN adapter whose tty appears at "
    "PATH (needs no kernel CAN); the daemon uses devices.can.interface = 'slcan', channel PATH. "
    "Without this or --can-channel the PC104 is not simulated.",
)
@click.option("--pty-dir", type=click.Path(file_okay=False), default=None)
@click.option("--write-config", type=click.Path(dir_okay=False, path_type=Path), default=None)
@click.option("--duration-s", type=click.FloatRange(min=0.0, min_open=True), default=None)
@click.option(
    "--ready-fd",
    type=click.IntRange(min=0),
    default=None,
    help="Write 'ready' to this inherited file descriptor once every twin is up (for the "
    "daemon that starts the simulated vehicle); the endpoint table is then not printed.",
)
@click.option(
    "--exit-on-stdin-eof", is_flag=True, help="Stop when standard input ends (the parent died)."
)
@click.option(
    "--bench-socket",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Listen here for bench requests (press a panel button, pull a cable, silence the "
    "PC104, observe what the twins were told): see appliance/sim/bench.py. Put it in a "
    "directory only you can write to.",
)
@click.pass_context
def sim(
    ctx: click.Context,
    config_name: str,
    can_channel: str | None,
    can_slcan: str | None,
    pty_dir: str | None,
    write_config: Path | None,
    duration_s: float | None,
    ready_fd: int | None,
    exit_on_stdin_eof: bool,
    bench_socket: Path | None,
) -> None:
    """Run the simulated vehicle and print its endpoints (and a config for `dbw run`).

    With a subcommand (`dbw sim dock`), run that instead.
    """
    if ctx.invoked_subcommand is not None:
        return
    try:
        config = load_config(config_name)
    except ConfigError as exc:
        click.echo(exc.render(), err=True)
        sys.exit(2)
    if can_channel and can_slcan:
        click.echo("give --can-channel or --can-slcan, not both", err=True)
        sys.exit(2)
    can: CanEndpoint | None = None
    if can_channel:
        can = CanEndpoint(interface=CanInterface.SOCKETCAN, channel=can_channel)
    elif can_slcan:
        os.makedirs(os.path.dirname(os.path.abspath(can_slcan)), exist_ok=True)
        can = CanEndpoint(interface=CanInterface.SLCAN, channel=can_slcan)
    structlog.contextvars.bind_contextvars(process="sim")
    sys.exit(
        asyncio.run(
            run_simulator(
                config,
                can,
                pty_dir,
                write_config,
                duration_s,
                ready_fd=ready_fd,
                exit_on_stdin_eof=exit_on_stdin_eof,
                bench_socket=bench_socket,
            )
        )
    )
