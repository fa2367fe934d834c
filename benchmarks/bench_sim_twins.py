"""Cost of the simulated devices' hot paths: what the simulation process spends per scan/tick.

Two LMS111 twins at 50 Hz (100 scans/s) and the PC104 twin at 200 Hz share one process with
the world, so each must be cheap. Figures (median, p99, min, max):

* ``encode``: one framed ``sSN LMDscandata`` telegram as a twin sends it to a subscriber
  (`DeviceModel.telegram` + `Lms111Connection.send_scan`), DIST1 + RSSI1 (16 bit, the
  default data configuration), per dialect and resolution (541 beams at 0.5°, 1081 at 0.25°);
* ``build``: `DeviceModel.measure` with the world stubbed out (precomputed ranges): the
  channel arrays and the `Scan` object, without ray casting;
* ``twin scan``: what one scan period costs a twin with one subscriber: ray casting the
  launcher site from a moving pose, the build and the encode (`Lms111Twin.device.measure`,
  then the telegram);
* ``PC104 tick``: `Pc104TwinCore.tick` every 5 ms with a command frame decoded every 20 ms
  (`on_frame`: STRAIGHT 1 m/s after a STOP, or STOP throughout), the world stepped alongside
  but not timed (in the daemon the world is its own service); the frames due (five types,
  20-100 ms) are encoded here. Most ticks send nothing, so the figure per 20 ms cycle (four
  ticks) is printed too. Standing still, every report but the inclinometer's repeats.

The last line adds it up for the daemon's simulated vehicle: two CoLa-A twins at 50 Hz /
0.5° plus the PC104 twin driving, as a percentage of one core (from the medians; the PC104's
per 20 ms cycle).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from appliance.config import load_config
from appliance.sim import Pose2D, load_site
from appliance.sim.twins.lms111 import Lms111Twin
from appliance.sim.twins.pc104_core import Pc104TwinCore
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from benchmarks.stats import summarize
from drivers.lms111 import Dialect, Lms111Connection
from drivers.lms111.mounted import mount_pose
from drivers.lms111.replies import ScanConfig
from drivers.lms111.twin_device import DeviceModel
from drivers.pc104 import protocol
from drivers.pc104.messages import MotionCommand, MotionPattern

WARMUP = 100
SAMPLES = 2000
MODES = ((50.0, 0.5), (25.0, 0.25))  # (Hz, deg): 541 and 1081 beams
PC104_TICK_S = 0.005


def _time_ms(operation: Callable[[int], object], samples: int = SAMPLES) -> list[float]:
    for i in range(WARMUP):
        operation(i)
    durations = []
    for i in range(samples):
        start = time.perf_counter_ns()
        operation(WARMUP + i)
        durations.append((time.perf_counter_ns() - start) / 1e6)
    return durations


def _stub_world(
    beams: int,
) -> Callable[[float, npt.NDArray[np.float64]], tuple[npt.NDArray[np.float64], ...]]:
    """Ranges 0.5-20 m with 5 % dropouts and remission 0.1-1, as the ray caster returns."""
    rng = np.random.default_rng(7)
    ranges = rng.uniform(0.5, 20.0, beams)
    ranges[rng.random(beams) < 0.05] = 0.0
    remission = np.where(ranges > 0, rng.uniform(0.1, 1.0, beams), 0.0)
    return lambda _t_s, _angles: (ranges, remission)


def bench_encode_and_build(dialect: Dialect, hz: float, deg: float) -> list[str]:
    config = ScanConfig.from_si(hz, deg)
    beams = (config.stop_angle_10000th_deg - config.start_angle_10000th_deg) // round(
        deg * 10_000
    ) + 1
    device = DeviceModel(_stub_world(beams), dialect=dialect, config=config)
    connection = Lms111Connection(dialect)
    scan = device.measure(1.0)
    assert scan is not None
    size = len(connection.send_scan(device.telegram(scan)))
    label = f"{dialect.value} {beams} beams"
    return [
        summarize(
            f"encode {label} ({size} B)",
            _time_ms(lambda _i: connection.send_scan(device.telegram(scan))),
            "ms",
        ),
        summarize(
            f"build {label} (world stubbed)",
            _time_ms(lambda i: device.measure(1.0 + i * 0.02)),
            "ms",
        ),
    ]


def _approach(t_s: float) -> Pose2D:
    """Drive towards the launcher and back at 1 m/s (bench_lms111_stream's path)."""
    return Pose2D(-16.0 + abs((t_s % 16.0) - 8.0), 0.3, math.radians(2.0))


def bench_twin_scan(dialect: Dialect, hz: float, deg: float) -> tuple[str, float]:
    twin = Lms111Twin(
        load_site("launcher"),
        mount_pose(load_config("sim").geometry.scanner_left_mount),
        _approach,
        dialect=dialect,
        scan_frequency_hz=hz,
        angular_resolution_deg=deg,
    )
    device = twin.device
    connection = Lms111Connection(dialect)
    period_s = device.period_s

    def one_scan(i: int) -> None:
        scan = device.measure(1.0 + i * period_s)
        assert scan is not None
        connection.send_scan(device.telegram(scan))

    samples = _time_ms(one_scan)
    beams = len(device.beam_angles_10000th_deg())
    line = summarize(
        f"twin scan {dialect.value} {beams} beams (ray cast + build + encode)", samples, "ms"
    )
    return line, float(np.median(samples))


def bench_pc104_tick(driving: bool) -> tuple[str, float]:
    """Ticks of a PC104 twin whose vehicle drives at 1 m/s (or stands: every report repeats)."""
    world = SimWorld(VehicleParams.from_config(load_config("sim")))
    core = Pc104TwinCore(world)
    stop = MotionCommand.stop()
    command = MotionCommand(MotionPattern.STRAIGHT, 1.0) if driving else stop
    ticks_per_command = round(0.02 / PC104_TICK_S)

    def tick(i: int) -> None:
        t_s = i * PC104_TICK_S
        if i % ticks_per_command == 0:  # STOP first: the twin moves only after one
            counter = (i // ticks_per_command) % protocol.COUNTER_MODULO
            core.on_frame(*protocol.encode(command if i > 40 else stop, counter), t_s)
        core.tick(t_s)

    # World stepping is not part of the twin's tick: do it outside the timed region.
    for i in range(4 * WARMUP):
        world.advance_to(i * PC104_TICK_S)
        tick(i)
    samples = []
    for i in range(4 * WARMUP, 4 * (WARMUP + SAMPLES)):
        world.advance_to(i * PC104_TICK_S)
        start = time.perf_counter_ns()
        tick(i)
        samples.append((time.perf_counter_ns() - start) / 1e6)
    assert (world.state.speed_mps > 0.5) is driving
    per_cycle = np.add.reduceat(samples, np.arange(0, len(samples), ticks_per_command)).tolist()
    what = "driving at 1 m/s" if driving else "standing still"
    lines = [
        summarize(f"PC104 tick, {what} (5 ms; a command every 4th tick)", samples, "ms"),
        summarize(f"PC104 20 ms cycle, {what} (1 command in, 3-5 frames out)", per_cycle, "ms"),
    ]
    return "\n".join(lines), float(np.median(per_cycle)) / ticks_per_command


def main() -> None:
    for hz, deg in MODES:
        for dialect in Dialect:
            for line in bench_encode_and_build(dialect, hz, deg):
                print(line)
    twin_ms: dict[tuple[Dialect, float], float] = {}
    for hz, deg in MODES:
        for dialect in Dialect:
            line, median_ms = bench_twin_scan(dialect, hz, deg)
            twin_ms[(dialect, deg)] = median_ms
            print(line)
    line, tick_ms = bench_pc104_tick(driving=True)
    print(line)
    print(bench_pc104_tick(driving=False)[0])
    scans_ms = 2 * 50 * twin_ms[(Dialect.COLA_A, 0.5)]
    ticks_ms = tick_ms / PC104_TICK_S
    print(
        "daemon's simulated devices (2 CoLa-A twins at 50 Hz / 0.5° + PC104 at 200 Hz), "
        f"from the medians: {(scans_ms + ticks_ms) / 10:.1f} % of one core "
        f"(scanners {scans_ms / 10:.1f} %, PC104 {ticks_ms / 10:.1f} %)"
    )


if __name__ == "__main__":
    main()
