"""The GNSS/INS receiver in the daemon: the simulated receiver on a pty, the client, the
epoch assembler, the ``gnss.pose`` topic, the control inputs and the status lines.

The truth is the simulated world's: the vehicle stands still at its start pose (its
brakes are on until somebody engages), so every fix must scatter around the antenna's
position computed here from that pose and the configured lever arm.
"""

from __future__ import annotations

import asyncio
import math
import os
import re
import shutil
import socket
import tempfile
import tomllib
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.cli.sim import daemon_config
from appliance.config import VehicleConfig, load_config
from appliance.config.models import Positioning, SimPlacement
from appliance.daemon import Daemon
from appliance.gnss_input import GNSS_POSE_TOPIC, NO_ORIGIN
from appliance.localization.gnss_pose import GnssPose
from appliance.sim.twins.gnss import GnssTwin
from appliance.sim.vehicle import VehicleState
from appliance.sim_process import SimProcess
from appliance.simulator import antenna_truth, build_simulator
from appliance.supervisor import ServiceState
from appliance.vehicle_io import VehicleIO, _build_gnss, link_summary
from drivers.gnss.sentences import FixQuality
from drivers.topics import Sample
from safety.watchdog import RestartPolicy
from tests.runtime.inline import inline_sim

ORIGIN = {"lat_deg": 42.4591, "lon_deg": -71.2674, "alt_m": 100.0}
NOISE_M = 0.05  # GnssTwinParams' default 1-sigma per axis
UP_LINE = re.compile(
    r"^up (?P<rate>\d+\.\d) fixes/s, quality RTK_FIXED, sigma 0\.05 m, 16 sats, rejects 0$"
)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def gnss_config(
    *,
    origin: bool = True,
    forward_m: float = 0.0,
    left_m: float = 0.0,
    placement: SimPlacement = SimPlacement.INLINE,
) -> VehicleConfig:
    """The sim profile with a simulated receiver (and scanners on free ports: another
    daemon may be running on this machine)."""
    data: dict[str, Any] = load_config("sim").model_dump(mode="json")
    data["devices"]["gnss"] = {"port": "sim://gnss", "receiver_latency_s": 0.0}
    data["devices"]["lms111_left"]["port"] = free_port()
    data["devices"]["lms111_right"]["port"] = free_port()
    data["positioning"]["origin"] = dict(ORIGIN) if origin else None
    data["positioning"]["antenna_forward_m"] = forward_m
    data["positioning"]["antenna_left_m"] = left_m
    data["simulation"]["placement"] = str(placement)
    config = VehicleConfig.model_validate(data)
    return inline_sim(config) if placement is SimPlacement.INLINE else config


@asynccontextmanager
async def running(config: VehicleConfig) -> AsyncIterator[Daemon]:
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")
    daemon = Daemon(config, control_socket=str(Path(directory) / "control.sock"))
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        yield daemon
    finally:
        daemon.request_stop("test over")
        result = await asyncio.wait_for(run, 10.0)
        shutil.rmtree(directory, ignore_errors=True)
        assert result.exit_code == 0, result.reason


async def wait_until(predicate: Callable[[], bool], timeout_s: float = 5.0) -> None:
    async def poll() -> None:
        while not predicate():
            await asyncio.sleep(0.01)

    await asyncio.wait_for(poll(), timeout_s)


def now_s() -> float:
    return asyncio.get_running_loop().time()


def gnss_twin(daemon: Daemon) -> GnssTwin:
    assert daemon.io.simulator is not None
    twin = daemon.io.simulator.gnss_twin
    assert twin is not None
    return twin


async def test_fixes_arrive_at_10_hz_where_the_simulated_antenna_is() -> None:
    forward_m, left_m = 1.5, 0.4
    config = gnss_config(forward_m=forward_m, left_m=left_m)
    samples: list[Sample[Any]] = []
    async with running(config) as daemon:
        io = daemon.io
        assert io.gnss is not None and io.simulator is not None
        topic = io.topics.get(GNSS_POSE_TOPIC)
        assert topic is io.gnss.topic
        await asyncio.wait_for(topic.wait_next(), 5.0)
        topic.subscribe(samples.append)
        await asyncio.sleep(2.5)
        start = io.simulator.world.state
        # What the control core is given: the newest epoch and its number.
        inputs = daemon.control.inputs.read(now_s())
        latest = topic.latest()
        assert latest is not None
        assert inputs.gnss_seq == latest.seq and inputs.gnss is latest.value
        doc = daemon.status_document()
        link = link_summary(io)["gnss"]
        assert daemon.supervisor.records["gnss"].spec.critical is False

    # The world's true pose, and the antenna on it, written out here.
    sim = config.simulation
    assert math.hypot(start.x_m - sim.start_x_m, start.y_m - sim.start_y_m) < 1e-3
    yaw = math.radians(sim.start_yaw_deg)
    east_m = sim.start_x_m + forward_m * math.cos(yaw) - left_m * math.sin(yaw)
    north_m = sim.start_y_m + forward_m * math.sin(yaw) + left_m * math.cos(yaw)

    poses = [s.value for s in samples]
    assert all(isinstance(p, GnssPose) for p in poses)
    assert [s.seq for s in samples] == list(range(samples[0].seq, samples[-1].seq + 1))
    span_s = samples[-1].stamp_s - samples[0].stamp_s
    rate_hz = (len(samples) - 1) / span_s
    assert 9.0 <= rate_hz <= 11.0, rate_hz
    n = len(poses)
    mean_e = sum(p.east_m for p in poses) / n
    mean_n = sum(p.north_m for p in poses) / n
    # The mean within 4 sigma of the mean (plus a step of the world's pose), each fix
    # within 5 sigma, and the scatter the configured noise, not zero nor a jump.
    assert math.hypot(mean_e - east_m, mean_n - north_m) < 4 * NOISE_M / math.sqrt(n) + 0.005
    assert max(math.hypot(p.east_m - east_m, p.north_m - north_m) for p in poses) < 5 * NOISE_M
    spread_e = math.sqrt(sum((p.east_m - mean_e) ** 2 for p in poses) / (n - 1))
    assert 0.5 * NOISE_M < spread_e < 1.6 * NOISE_M
    for pose in poses:
        assert pose.quality is FixQuality.RTK_FIXED and pose.satellites == 16
        assert pose.yaw_rad is not None and abs(pose.yaw_rad - yaw) < math.radians(0.6)
        assert pose.sigma_worst_m == pytest.approx(NOISE_M, abs=1e-3)
    # dbw status: the topic's age (10 Hz: at most a period and the delivery), the link.
    age_s = doc["inputs"][GNSS_POSE_TOPIC]["age_s"]
    assert age_s is not None and 0.0 <= age_s < 0.25
    match = UP_LINE.match(link)
    assert match is not None, link
    assert 9.0 <= float(match["rate"]) <= 11.0


async def test_an_unplugged_receiver_goes_stale_and_down_and_recovers_on_replug() -> None:
    config = gnss_config()
    max_age_s = config.positioning.max_fix_age_s
    async with running(config) as daemon:
        io = daemon.io
        assert io.gnss is not None
        topic = io.gnss.topic
        await asyncio.wait_for(topic.wait_next(), 5.0)
        assert link_summary(io)["gnss"].startswith("up ")
        gnss_twin(daemon).unplug()
        await wait_until(lambda: topic.age_s(now_s()) > max_age_s + 0.1, 3.0)
        before = topic.latest()
        assert before is not None
        assert link_summary(io)["gnss"].startswith("down: ")
        assert daemon.status_document()["inputs"][GNSS_POSE_TOPIC]["age_s"] > max_age_s
        # The core still sees the last epoch (its age tells it not to steer by it).
        assert daemon.control.inputs.read(now_s()).gnss_seq == before.seq
        # Not critical, and the client keeps trying by itself: nothing restarts or latches.
        record = daemon.supervisor.records["gnss"]
        assert record.state is ServiceState.RUNNING and record.budget.total_restarts == 0
        assert daemon.supervisor.latched_error is None

        gnss_twin(daemon).replug()
        after = await asyncio.wait_for(topic.wait_next(before.seq), 5.0)
        assert after.age_s(now_s()) < 0.25
        await wait_until(lambda: link_summary(io)["gnss"].startswith("up "), 2.0)
        assert io.gnss.client.health().reconnects >= 1


async def test_a_failing_gnss_service_is_restarted_by_the_supervisor() -> None:
    async with running(gnss_config()) as daemon:
        gnss = daemon.io.gnss
        assert gnss is not None and gnss.assembler is not None
        topic = gnss.topic
        await asyncio.wait_for(topic.wait_next(), 5.0)
        update = gnss.assembler.update
        failures = [RuntimeError("assembler bug")]

        def failing_once(event: Any, receive_time_s: float) -> Any:
            if failures:
                raise failures.pop()
            return update(event, receive_time_s)

        gnss.assembler.update = failing_once  # type: ignore[method-assign]
        record = daemon.supervisor.records["gnss"]
        await wait_until(lambda: record.budget.total_restarts >= 1, 3.0)
        assert "assembler bug" in record.last_error
        last = topic.latest()
        assert last is not None
        await asyncio.wait_for(topic.wait_next(last.seq), 5.0)
        assert record.state is ServiceState.RUNNING
        assert daemon.supervisor.latched_error is None


async def test_without_an_origin_the_receiver_is_read_but_nothing_is_published() -> None:
    async with running(gnss_config(origin=False)) as daemon:
        gnss = daemon.io.gnss
        assert gnss is not None and gnss.assembler is None
        await wait_until(lambda: gnss.client.health().events_ok >= 20, 5.0)
        assert gnss.topic.latest() is None
        link = link_summary(daemon.io)["gnss"]
        assert link.startswith("up ") and link.endswith(NO_ORIGIN), link
        inputs = daemon.control.inputs.read(now_s())
        assert inputs.gnss is None and inputs.gnss_seq is None
        assert daemon.supervisor.records["gnss"].state is ServiceState.RUNNING


async def test_the_receiver_in_the_simulated_vehicles_own_process() -> None:
    async with running(gnss_config(placement=SimPlacement.PROCESS)) as daemon:
        io = daemon.io
        assert io.sim_process is not None and io.gnss is not None
        assert io.gnss.client.port == os.path.join(io.sim_process.directory, "gnss")
        first = await asyncio.wait_for(io.gnss.topic.wait_next(), 30.0)
        later = await asyncio.wait_for(io.gnss.topic.wait_next(first.seq + 4), 2.0)
        assert isinstance(later.value, GnssPose)
        start = io.sim_process.config.simulation
        assert (
            math.hypot(later.value.east_m - start.start_x_m, later.value.north_m - start.start_y_m)
            < 5 * NOISE_M
        )


def test_a_daemon_without_a_receiver_has_no_gnss_service() -> None:
    config = inline_sim(load_config("sim"))
    assert config.devices.gnss is None
    daemon = Daemon(config, control_socket="/nonexistent/control.sock")
    try:
        io = daemon.io
        assert io.gnss is None
        assert io.simulator is not None and io.simulator.gnss_twin is None
        assert "gnss" not in daemon.supervisor.records
        assert "sim.gnss" not in daemon.supervisor.records
        inputs = daemon.control.inputs.read(0.0)
        assert inputs.gnss is None and inputs.gnss_seq is None
        # Reading the inputs did not invent the topic either.
        assert GNSS_POSE_TOPIC not in io.topics.ages_s(0.0)
        assert "gnss" not in link_summary(io)
    finally:
        daemon.io.close()


def test_a_simulated_receiver_without_the_simulation_is_refused() -> None:
    config = gnss_config().model_copy(
        update={"simulation": load_config("sim").simulation.model_copy(update={"enabled": False})}
    )
    with pytest.raises(ValueError, match="simulated receiver"):
        _build_gnss(config, VehicleIO(), RestartPolicy(), None)


def test_dbw_sim_writes_the_receivers_pty_into_the_daemon_config() -> None:
    config = gnss_config(placement=SimPlacement.PROCESS)
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")
    simulator = build_simulator(config, RestartPolicy(), can=None, pty_directory=directory)
    try:
        twin = simulator.gnss_twin
        assert twin is not None
        path = os.path.join(directory, "gnss")
        assert twin.port_path == path == simulator.port_path("sim://gnss")
        assert os.path.realpath(path).startswith("/dev/pts/")
        written = tomllib.loads(daemon_config(config, simulator, None))
        assert written["devices"]["gnss"]["port"] == path
        assert written["simulation"]["enabled"] is False
        VehicleConfig.model_validate(written)  # `dbw run` can load it
        # The daemon's side of a child process finds the same name in its directory.
        assert SimProcess(config, directory).port_path("sim://gnss") == path
        # The twin's frame is the configured one.
        assert twin.synth.frame.origin_lat_deg == ORIGIN["lat_deg"]
        assert twin.synth.frame.origin_lon_deg == ORIGIN["lon_deg"]
    finally:
        simulator.close()
    assert not os.path.exists(path)
    shutil.rmtree(directory, ignore_errors=True)


@given(
    x_m=st.floats(-500, 500),
    y_m=st.floats(-500, 500),
    yaw_rad=st.floats(-10, 10),
    forward_m=st.floats(-20, 20),
    left_m=st.floats(-5, 5),
)
def test_the_antenna_sits_at_its_lever_arm_in_the_vehicle_frame(
    x_m: float, y_m: float, yaw_rad: float, forward_m: float, left_m: float
) -> None:
    state = VehicleState(x_m=x_m, y_m=y_m, yaw_rad=yaw_rad, speed_mps=1.25)
    positioning = Positioning(antenna_forward_m=forward_m, antenna_left_m=left_m)
    east_m, north_m, yaw, speed_mps = antenna_truth(state, positioning)
    # Back into the vehicle frame: the offset seen along and across the heading.
    de, dn = east_m - x_m, north_m - y_m
    along_m = de * math.cos(yaw_rad) + dn * math.sin(yaw_rad)
    across_m = -de * math.sin(yaw_rad) + dn * math.cos(yaw_rad)
    assert along_m == pytest.approx(forward_m, abs=1e-9)
    assert across_m == pytest.approx(left_m, abs=1e-9)
    assert (yaw, speed_mps) == (yaw_rad, 1.25)
