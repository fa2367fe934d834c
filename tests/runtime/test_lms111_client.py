"""The LMS111 client against the twin over real TCP on 127.0.0.1, in real time.

Each test runs one twin and one client in the test's event loop and breaks the link the way
users of LMS1xx drivers report it breaking: dropped and stalled connections, telegrams cut
into pieces or glued together, line noise, corrupted telegrams, refusals while configuring,
a refused login, a scanner still booting, one that is not ready, one that reboots. Deadlines
and backoffs are short (constructor arguments) so the whole file runs in a few seconds.
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from structlog.testing import capture_logs

from appliance.config.models import Lms111Endpoint, SensorMount
from appliance.sim import Circle, Pose2D, Segment, Site, load_site
from appliance.sim.twins.lms111 import Lms111Twin, TwinFaults
from drivers.lms111 import Dialect
from drivers.lms111.client import Lms111Client, Lms111ConfigError, Lms111LoginError
from drivers.lms111.handshake import probe
from drivers.lms111.mounted import MountedScan, mount_pose
from drivers.topics import Sample, Topic

LEFT_MOUNT = SensorMount(x_m=4.5, y_m=1.1, yaw_deg=45.0)
BOTH = pytest.mark.parametrize("dialect", list(Dialect), ids=lambda d: d.value)


class RecordingTopic(Topic[MountedScan]):
    """A topic that also keeps every sample, so a test can check nothing was lost."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.all: list[MountedScan] = []

    def publish(self, value: MountedScan, stamp_s: float) -> Sample[MountedScan]:
        self.all.append(value)
        return super().publish(value, stamp_s)


@dataclass
class Rig:
    twin: Lms111Twin
    client: Lms111Client
    topic: RecordingTopic
    task: asyncio.Task[None]
    beats: list[float] = field(default_factory=list)

    @property
    def scans(self) -> list[MountedScan]:
        return self.topic.all

    async def until(self, condition: Callable[[], bool], timeout_s: float = 3.0) -> float:
        """Wait until ``condition()``; the seconds it took. Fails the test on timeout."""
        started_s = time.monotonic()
        while not condition():
            if self.task.done():
                self.task.result()  # surface the client's exception
            if time.monotonic() - started_s > timeout_s:
                pytest.fail(f"timed out after {timeout_s} s; health: {self.client.health}")
            await asyncio.sleep(0.002)
        return time.monotonic() - started_s

    async def scans_after(self, count: int, timeout_s: float = 3.0) -> None:
        target = len(self.scans) + count
        await self.until(lambda: len(self.scans) >= target, timeout_s)


def _pose_behind_launcher(_: float) -> Pose2D:
    return Pose2D(-10.0, 0.3, math.radians(2.0))


@asynccontextmanager
async def rig(
    *,
    dialect: Dialect = Dialect.COLA_A,
    frequency_hz: int = 50,
    resolution_deg: float = 0.5,
    faults: TwinFaults | None = None,
    site: Site | None = None,
    pose: Callable[[float], Pose2D] = _pose_behind_launcher,
    noise_sigma_m: float = 0.012,
    start_client: bool = True,
    device_time_offset_us: int = 0,
    **client_options: Any,
) -> AsyncIterator[Rig]:
    twin = Lms111Twin(
        site or load_site("launcher"),
        mount_pose(LEFT_MOUNT),
        pose,
        name="left",
        dialect=dialect,
        faults=faults,
        seed=3,
        range_bias_m=0.01,
        noise_sigma_m=noise_sigma_m,
        device_time_offset_us=device_time_offset_us,
    )
    await twin.start()
    # model_construct: a test may ask for a mode the config would refuse, to check that the
    # client also survives a device that refuses it (another firmware, a hand-made config).
    endpoint = Lms111Endpoint.model_construct(
        host="127.0.0.1",
        port=twin.port,
        scan_frequency_hz=frequency_hz,
        angular_resolution_deg=resolution_deg,
    )
    options: dict[str, Any] = {
        "connect_timeout_s": 0.5,
        "request_timeout_s": 0.3,
        "backoff_initial_s": 0.02,
        "backoff_cap_s": 0.2,
        "ready_poll_s": 0.05,
        "boot_wait_s": 5.0,
    }
    options.update(client_options)
    topic = RecordingTopic("scan.left")
    client = Lms111Client("left", endpoint, LEFT_MOUNT, topic, dialect=dialect, **options)
    beats: list[float] = []
    task = asyncio.create_task(client.run(lambda: beats.append(time.monotonic())))
    if not start_client:
        task.cancel()
    try:
        yield Rig(twin, client, topic, task, beats)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await twin.stop()


def events(logs: Sequence[Mapping[str, Any]], name: str) -> list[Mapping[str, Any]]:
    return [entry for entry in logs if entry["event"] == name]


def assert_counters_continuous(scans: list[MountedScan], skipped_by_twin: int = 0) -> None:
    """Every scan the twin sent arrived. The twin itself skips scans (and says so) only when
    its event loop fell more than a few periods behind, as on a loaded CI machine."""
    counters = np.array([s.scan.scan_counter for s in scans], dtype=np.int64)
    telegrams = np.array([s.scan.telegram_counter for s in scans], dtype=np.int64)
    assert np.all(np.diff(telegrams) % 65536 == 1), telegrams
    gaps = np.diff(counters) % 65536 - 1
    assert np.all(gaps >= 0), counters
    assert int(gaps.sum()) <= skipped_by_twin, counters


# ---- scans flow ------------------------------------------------------------------------


@BOTH
@pytest.mark.parametrize(
    ("frequency_hz", "resolution_deg", "beams"), [(50, 0.5, 541), (25, 0.25, 1081)]
)
async def test_scans_flow_at_the_configured_rate_and_resolution(
    dialect: Dialect, frequency_hz: int, resolution_deg: float, beams: int
) -> None:
    async with rig(dialect=dialect, frequency_hz=frequency_hz, resolution_deg=resolution_deg) as r:
        await r.scans_after(1)
        first = len(r.scans)
        started_s = time.monotonic()
        await asyncio.sleep(1.0)
        elapsed_s = time.monotonic() - started_s
        health = r.client.health
    scans = r.scans[first:]
    assert len(scans) == pytest.approx(frequency_hz * elapsed_s, abs=3)
    assert health.scans_per_s == pytest.approx(frequency_hz, abs=3)
    assert health.connected and health.configured and health.state == "streaming"
    assert health.dropped_scans <= r.twin.stats.scans_skipped
    assert (health.malformed_telegrams, health.reconnects) == (0, 0)
    assert len(r.beats) == health.scans_total
    assert_counters_continuous(r.scans, r.twin.stats.scans_skipped)
    scan = scans[-1].scan
    assert len(scan.ranges_m) == beams
    assert scan.angular_step_rad == pytest.approx(math.radians(resolution_deg))
    assert scan.angles_rad[0] == pytest.approx(math.radians(-45.0))
    assert scan.angles_rad[-1] == pytest.approx(math.radians(225.0))
    assert scan.scan_frequency_hz == frequency_hz
    assert scan.intensities is not None and scan.intensities.max() > 0
    # Device time: exactly one period per scan, in µs, unwrapped.
    device_steps_us = np.diff([s.device_time_us for s in r.scans])
    assert np.all(np.abs(device_steps_us - 1e6 / frequency_hz) <= 1)
    assert r.topic.latest() is not None
    assert r.topic.age_s(time.monotonic()) < 3.0 / frequency_hz


async def test_device_time_is_unwrapped_across_the_32_bit_wrap() -> None:
    async with rig(device_time_offset_us=(1 << 32) - 300_000) as r:  # wraps 0.3 s after boot
        await r.until(lambda: len(r.scans) >= 5 and r.scans[-1].scan.device_time_us < 200_000)
        await r.scans_after(3)
    raw = np.array([s.scan.device_time_us for s in r.scans], dtype=np.int64)
    unwrapped = np.diff([s.device_time_us for s in r.scans])
    assert np.any(np.diff(raw) < 0)  # the raw clock did wrap
    assert np.all(unwrapped == 20_000)


# ---- link faults -----------------------------------------------------------------------


@BOTH
async def test_dropped_connection_reconnects_logs_in_configures_and_resumes(
    dialect: Dialect,
) -> None:
    with capture_logs() as logs:
        async with rig(dialect=dialect) as r:
            await r.scans_after(5)
            r.twin.drop_connections()
            took_s = await r.until(lambda: r.client.health.reconnects == 1)
            await r.scans_after(10)
            health = r.client.health
            requests = r.twin.stats.requests
    assert took_s < 1.0
    assert health.connected and health.configured and health.dropped_scans == 0
    assert requests["SetAccessMode"] == 2
    assert requests["mLMPsetscancfg"] == 2
    assert requests["LMDscandatacfg"] == 2
    assert requests["LMDscandata"] == 2  # the subscription, once per session
    assert len(events(logs, "lms111_link_lost")) == 1
    streaming = events(logs, "lms111_streaming")
    assert [e["reconnect"] for e in streaming] == [False, True]


async def test_silent_stall_is_detected_within_the_read_deadline() -> None:
    with capture_logs() as logs:
        async with rig(read_deadline_periods=3) as r:
            await r.scans_after(5)
            r.twin.stall_connections()  # the socket stays open, nothing more arrives
            await r.until(lambda: not r.client.health.configured, timeout_s=1.0)
            silent_s = r.client.health.scan_age_s
            await r.until(lambda: r.client.health.reconnects == 1)
            await r.scans_after(5)
    assert silent_s <= 3 * 0.020 + 0.030  # three periods, plus scheduling slack
    (lost,) = events(logs, "lms111_link_lost")
    assert "stalled" in lost["reason"]


async def test_our_own_blocked_event_loop_is_not_mistaken_for_a_stall() -> None:
    """The scanner keeps sending while this loop is blocked for 5 deadlines: no reconnect."""
    ready = threading.Event()
    holder: dict[str, Any] = {}

    def serve_in_thread() -> None:
        async def serve() -> None:
            twin = Lms111Twin(load_site("launcher"), mount_pose(LEFT_MOUNT), _pose_behind_launcher)
            await twin.start()
            holder["port"], holder["loop"] = twin.port, asyncio.get_running_loop()
            holder["stop"] = stop = asyncio.Event()
            ready.set()
            await stop.wait()
            await twin.stop()

        asyncio.run(serve())

    thread = threading.Thread(target=serve_in_thread, daemon=True)
    thread.start()
    assert ready.wait(5.0)
    topic = RecordingTopic("scan.left")
    endpoint = Lms111Endpoint(host="127.0.0.1", port=holder["port"])
    client = Lms111Client("left", endpoint, LEFT_MOUNT, topic, request_timeout_s=0.5)
    task = asyncio.create_task(client.run(lambda: None))
    try:
        while len(topic.all) < 5:
            await asyncio.sleep(0.005)
        time.sleep(0.3)  # noqa: ASYNC251  # a blocking neighbour: 15 periods, 5 deadlines
        await asyncio.sleep(0.2)
        health = client.health
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        holder["loop"].call_soon_threadsafe(holder["stop"].set)
        thread.join(5.0)
    assert health.reconnects == 0 and health.state == "streaming", health
    assert health.dropped_scans == 0  # late, but every one of them arrived
    assert_counters_continuous(topic.all)


@BOTH
async def test_fragmented_and_batched_telegrams_lose_nothing(dialect: Dialect) -> None:
    faults = TwinFaults(fragment=True, batch_telegrams=3)
    async with rig(dialect=dialect, faults=faults, read_deadline_periods=6) as r:
        await r.scans_after(1)
        await asyncio.sleep(1.0)
        health = r.client.health
    assert health.scans_total >= 40
    assert health.dropped_scans <= r.twin.stats.scans_skipped
    assert (health.malformed_telegrams, health.reconnects) == (0, 0)
    assert_counters_continuous(r.scans, r.twin.stats.scans_skipped)
    assert r.twin.stats.writes > 2 * r.twin.stats.telegrams_sent / 3  # really cut up


@BOTH
async def test_garbage_between_telegrams_is_counted_and_no_scan_is_lost(dialect: Dialect) -> None:
    with capture_logs() as logs:
        async with rig(dialect=dialect, faults=TwinFaults(garbage=True)) as r:
            await r.scans_after(30)
            health = r.client.health
            sent = r.twin.stats.garbage_bytes
    assert 0 < health.garbage_bytes <= sent
    assert health.dropped_scans <= r.twin.stats.scans_skipped
    assert (health.malformed_telegrams, health.reconnects) == (0, 0)
    assert_counters_continuous(r.scans, r.twin.stats.scans_skipped)
    assert len(events(logs, "lms111_garbage")) == 1  # one episode, not one line per read


@BOTH
async def test_corrupted_telegrams_are_counted_and_the_stream_continues(
    dialect: Dialect,
) -> None:
    with capture_logs() as logs:
        async with rig(dialect=dialect, faults=TwinFaults(corrupt_every=7)) as r:
            await r.scans_after(40)
            r.twin.faults.corrupt_every = 0
            await r.scans_after(3)
            health = r.client.health
            corrupted = r.twin.stats.corrupted
    assert corrupted >= 5
    assert health.malformed_telegrams == corrupted
    # each one leaves a scan counter gap (plus any the twin skipped itself under load)
    assert corrupted <= health.dropped_scans <= corrupted + r.twin.stats.scans_skipped
    assert health.reconnects == 0
    assert len(events(logs, "lms111_malformed_telegram")) == 1
    assert len(events(logs, "lms111_scans_dropped")) == 1


# ---- refusals are fatal, at once -----------------------------------------------------


@pytest.mark.parametrize(
    ("command", "code", "meaning"),
    [
        ("mLMPsetscancfg", 0x08, "buffer underflow"),
        ("LMDscandatacfg", 0x0A, "write access denied"),
        ("LMCstartmeas", 0x01, "access denied"),
    ],
)
async def test_sfa_while_configuring_raises_a_config_error_without_retrying(
    command: str, code: int, meaning: str
) -> None:
    with capture_logs() as logs:
        async with rig(faults=TwinFaults(fail_commands={command: code})) as r:
            await r.until(r.task.done, timeout_s=2.0)
            with pytest.raises(Lms111ConfigError) as info:
                r.task.result()
            connections = r.twin.stats.connections
            state = r.client.health.state
    assert info.value.command == command and info.value.code == code
    assert command in str(info.value) and meaning in str(info.value)
    assert connections == 1 and state == "failed"
    (refused,) = events(logs, "lms111_refused")
    assert refused["command"] == command


async def test_refused_login_raises_a_login_error() -> None:
    async with rig(faults=TwinFaults(refuse_login=True)) as r:
        await r.until(r.task.done, timeout_s=2.0)
        with pytest.raises(Lms111LoginError, match="SetAccessMode"):
            r.task.result()
        assert r.twin.stats.connections == 1


async def test_a_mode_the_lms111_does_not_have_is_refused_with_its_reason() -> None:
    async with rig(frequency_hz=50, resolution_deg=0.25) as r:
        await r.until(r.task.done, timeout_s=2.0)
        with pytest.raises(Lms111ConfigError, match="angular resolution error") as info:
            r.task.result()
    assert (info.value.command, info.value.code) == ("mLMPsetscancfg", 2)


# ---- a scanner coming up -----------------------------------------------------------------


@pytest.mark.parametrize("silent", [False, True], ids=["tcp-refused", "accepted-silent"])
async def test_a_booting_scanner_is_waited_for_quietly(silent: bool) -> None:
    faults = TwinFaults(boot_s=0.8, boot_silent=silent)
    with capture_logs() as logs:
        async with rig(faults=faults) as r:
            took_s = await r.until(lambda: len(r.scans) >= 3, timeout_s=3.0)
            health = r.client.health
    assert 0.8 <= took_s < 2.0
    assert health.reconnects == 0 and health.state == "streaming"
    assert len(events(logs, "lms111_waiting_for_scanner")) == 1
    assert not [e for e in logs if e["log_level"] in ("warning", "error")]


async def test_a_scanner_that_is_not_ready_is_waited_for() -> None:
    with capture_logs() as logs:
        async with rig(faults=TwinFaults(not_ready_s=0.5)) as r:
            await r.until(lambda: r.client.health.state == "not_ready", timeout_s=1.0)
            assert "not ready" in r.client.health.last_error
            assert r.client.health.connected and not r.client.health.configured
            took_s = await r.until(lambda: len(r.scans) >= 3, timeout_s=3.0)
            connections = r.twin.stats.connections
    assert took_s < 1.0 and connections == 1
    (not_ready,) = events(logs, "lms111_not_ready")
    assert not_ready["state"] == 5  # in preparation
    assert len(events(logs, "lms111_ready")) == 1


async def test_a_twin_restarted_on_the_same_port_is_reconnected() -> None:
    async with rig() as r:
        await r.scans_after(30)  # the device clock reads at least 0.6 s
        port = r.twin.port
        before = r.scans[-1]
        await r.twin.stop()
        await asyncio.sleep(0.3)
        await r.twin.start()
        assert r.twin.port == port
        await r.until(lambda: r.client.health.reconnects == 1)
        await r.scans_after(5)
        after = r.scans[-1]
    assert after.device_time_us < before.device_time_us  # a reboot: the clock restarted
    assert after.scan.scan_counter < before.scan.scan_counter
    assert r.client.health.dropped_scans == 0  # counters restart with the session


# ---- geometry --------------------------------------------------------------------------


async def test_a_wall_ahead_of_the_vehicle_appears_at_its_vehicle_frame_x() -> None:
    """A wall across x = 12 m and a post left of the vehicle, seen by the left scanner."""
    site = Site(
        segments=(Segment(12.0, -15.0, 12.0, 15.0, 0.8, "wall"),),
        circles=(Circle(6.0, 5.0, 0.3, 0.5, "post"),),
    )
    async with rig(site=site, pose=lambda _: Pose2D(0.0, 0.0, 0.0), noise_sigma_m=0.0) as r:
        await r.scans_after(2)
        scan = r.scans[-1]
    points = scan.points_vehicle_m()
    bias_m = 0.01  # the twin's fixed range bias
    on_wall = points[np.abs(points[:, 0] - 12.0) < 0.2]
    assert len(on_wall) > 50
    assert np.all(np.abs(on_wall[:, 0] - 12.0) < bias_m + 0.002)  # a straight wall, not slanted
    assert on_wall[:, 1].min() < -1.0 and on_wall[:, 1].max() > 3.0
    near_post = points[np.hypot(points[:, 0] - 6.0, points[:, 1] - 5.0) < 0.5]
    assert len(near_post) >= 2  # left is +y
    straight_ahead = np.argmin(np.abs(scan.angles_vehicle_rad))
    assert scan.scan.ranges_m[straight_ahead] > 0
    assert scan.mount == Pose2D(4.5, 1.1, math.radians(45.0))


# ---- probe -----------------------------------------------------------------------------


@BOTH
async def test_probe_reads_identity_status_and_configuration(dialect: Dialect) -> None:
    async with rig(dialect=dialect, start_client=False) as r:
        result = await probe("127.0.0.1", r.twin.port, timeout_s=1.0, dialect=dialect)
    assert result.errors == {}
    assert result.device_ident is not None and result.device_ident.name.startswith("LMS")
    assert result.location_name == "left"
    assert result.status is not None and result.status.measuring
    assert result.scan_config is not None and result.scan_config.scan_frequency_hz == 50
    text = json.dumps(result.to_dict())
    assert '"measuring": true' in text and '"angular_resolution_deg": 0.5' in text
