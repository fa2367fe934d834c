"""The serial client against the pty twin, end to end, and `dbw gnss probe/record` on it.

Real ptys, real pyserial, the real event loop: the twin is what a USB receiver is to the
client, down to the unplug (the pty is closed, its path vanishes, and a new one appears)."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import datetime as dt
import io
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pymap3d
import pytest
from click.testing import CliRunner

from appliance.cli.gnss import LineLog, ProbeStats, gnss, verdict
from appliance.sim.twins.gnss import GnssTwin, GnssTwinParams
from drivers.gnss import FixQuality, GgaFix, GstError, Heading, NmeaEvent, NmeaReceiver, Reject
from drivers.gnss.client import GnssClient
from tests.unit.gnss.lines import sentence, xor_checksum

POSE = (5.0, 7.0, 0.3, 4.0)  # east, north, yaw (ENU), speed
CLEAN = GnssTwinParams(position_noise_m=0.0, heading_noise_rad=0.0, rate_hz=20.0)
CLOCK_OFFSET_S = 5000.0  # the client's clock is not time.monotonic: stamps must come from it


def offset_clock() -> float:
    return time.monotonic() + CLOCK_OFFSET_S


async def wait_until(condition: Callable[[], bool], timeout_s: float = 3.0) -> None:
    deadline_s = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline_s, "timed out"
        await asyncio.sleep(0.005)


@dataclasses.dataclass
class Rig:
    twin: GnssTwin
    client: GnssClient
    received: list[tuple[NmeaEvent, float]]
    links: list[tuple[bool, str]]
    written_s: dict[float, float]  # epoch's UTC time of day -> client-clock time written
    beats: list[float]
    feeding: bool = True

    def ggas(self) -> list[tuple[GgaFix, float]]:
        return [(e, t) for e, t in self.received if isinstance(e, GgaFix)]


@contextlib.asynccontextmanager
async def rig_on(
    path: str, params: GnssTwinParams = CLEAN, *, beat_while_reconnecting: bool = False
) -> AsyncIterator[Rig]:
    twin = GnssTwin(path, params, seed=1)
    received: list[tuple[NmeaEvent, float]] = []
    links: list[tuple[bool, str]] = []
    beats: list[float] = []
    client = GnssClient(
        twin.port_path,
        lambda event, stamp_s: received.append((event, stamp_s)),
        max_age_s=0.2,
        backoff_initial_s=0.02,
        backoff_cap_s=0.1,
        on_link=lambda up, reason, now_s: links.append((up, reason)),
        clock=offset_clock,
        beat_while_reconnecting=beat_while_reconnecting,
    )
    rig = Rig(twin, client, received, links, {}, beats)

    async def feed() -> None:
        while True:
            if rig.feeding and client.connected:  # what is sent before the port opens is lost
                epoch = twin.update(time.monotonic(), *POSE)
                if epoch is not None:
                    rig.written_s[round(12 * 3600 + epoch.t_s, 2)] = offset_clock()
            await asyncio.sleep(0.005)

    async with asyncio.TaskGroup() as group:
        tasks = [
            group.create_task(feed()),
            group.create_task(client.run(lambda: beats.append(offset_clock()))),
        ]
        try:
            yield rig
        finally:
            for task in tasks:
                task.cancel()
            twin.close()


async def test_events_arrive_stamped_with_their_receive_time(tmp_path: Path) -> None:
    start_s = offset_clock()
    async with rig_on(str(tmp_path / "gnss")) as rig:
        await wait_until(lambda: len(rig.ggas()) >= 10)
        end_s = offset_clock()
        health = rig.client.health()
    stamps = [t for _, t in rig.received]
    assert stamps == sorted(stamps)
    assert start_s <= stamps[0] and stamps[-1] <= end_s  # from the injected clock
    kinds = {type(e) for e, _ in rig.received}
    assert {GgaFix, GstError, Heading} <= kinds and len(kinds) == 5
    expected = pymap3d.enu2geodetic(POSE[0], POSE[1], 0.0, 42.4591, -71.2674, 100.0)
    for gga, stamp_s in rig.ggas():
        assert gga.lat_deg == pytest.approx(float(expected[0]), abs=1e-8)  # ~1 mm
        assert gga.lon_deg == pytest.approx(float(expected[1]), abs=1e-8)
        assert gga.utc_time_of_day_s is not None
        written_s = rig.written_s[round(gga.utc_time_of_day_s, 2)]
        assert 0.0 <= stamp_s - written_s < 0.1  # received when written, not at some later poll
    assert health.connected and not health.stale and health.healthy
    assert health.events_ok == len(rig.received)
    assert health.events_by_sentence["GGA"] >= 10
    assert health.rejects == {} and health.error_count == 0 and health.reconnects == 0
    assert health.bytes_received > 10 * 5 * 20
    assert health.last_event_age_s < 0.1
    assert rig.links == [(True, "open")]


async def test_unplug_reports_link_down_and_replug_resumes(tmp_path: Path) -> None:
    params = dataclasses.replace(CLEAN, corrupt_fraction=0.2)
    async with rig_on(str(tmp_path / "gnss"), params) as rig:
        client = rig.client
        await wait_until(lambda: client.rejects()[Reject.CHECKSUM] >= 2)
        rejects_before = client.rejects()[Reject.CHECKSUM]
        rig.twin.unplug()
        await wait_until(lambda: not client.connected)
        up, reason = rig.links[-1]
        assert not up and ("EOF" in reason or "Input/output error" in reason)
        count = len(rig.received)
        await asyncio.sleep(0.3)  # several reopen attempts fail meanwhile
        health = client.health()
        assert not health.connected and health.stale
        assert health.last_error.startswith("open failed") and "No such file" in health.last_error
        assert len(rig.received) == count
        rig.twin.replug()
        await wait_until(lambda: len(rig.received) > count + 5)
        health = client.health()
    assert health.connected and health.reconnects == 1
    assert [up for up, _ in rig.links] == [True, False, True]
    assert health.rejects[Reject.CHECKSUM] >= rejects_before  # counts survive the reconnect


async def test_garbage_and_damaged_lines_are_counted_and_survived(tmp_path: Path) -> None:
    params = dataclasses.replace(CLEAN, corrupt_fraction=0.3, split_fraction=0.5)
    async with rig_on(str(tmp_path / "gnss"), params) as rig:
        await wait_until(lambda: len(rig.ggas()) >= 3)
        rig.twin.inject_noise(b"\x00\xff\xfe line noise\r\n$GPGGA,no checksum\r\n")
        await wait_until(lambda: len(rig.ggas()) >= 8)
        rig.feeding = False
        await asyncio.sleep(0.1)  # the last bytes written are read
        health = rig.client.health()
    synth = rig.twin.synth
    assert health.rejects == {
        Reject.CHECKSUM: synth.corrupted_lines,
        Reject.NO_START: 1,
        Reject.NO_CHECKSUM: 1,
    }
    assert health.events_ok == len(rig.received) == synth.lines - synth.corrupted_lines
    assert health.error_count == synth.corrupted_lines + 2
    assert health.garbage_bytes == len(b"\x00\xff\xfe line noise")
    assert health.last_bad_reason in ("checksum", "no_checksum")
    assert health.connected


async def test_a_line_split_across_reads_is_joined_and_stamped_at_its_end(tmp_path: Path) -> None:
    async with rig_on(str(tmp_path / "gnss")) as rig:
        await wait_until(lambda: len(rig.received) >= 5)
        rig.feeding = False
        await asyncio.sleep(0.05)
        count = len(rig.received)
        line = sentence("GPHDT,123.456,T")
        rig.twin.link.write(line[:9])
        await asyncio.sleep(0.1)
        assert len(rig.received) == count
        completed_s = offset_clock()
        rig.twin.link.write(line[9:])
        await wait_until(lambda: len(rig.received) == count + 1)
    event, stamp_s = rig.received[-1]
    assert isinstance(event, Heading) and event.heading_rad == pytest.approx(math.radians(123.456))
    assert completed_s <= stamp_s < completed_s + 0.1


async def test_silence_is_stale_and_stops_the_heartbeat(tmp_path: Path) -> None:
    async with rig_on(str(tmp_path / "gnss")) as rig:
        await wait_until(lambda: rig.client.health().healthy and len(rig.beats) > 2)
        rig.feeding = False
        await wait_until(lambda: rig.client.health().stale)
        await asyncio.sleep(0.05)
        beats = len(rig.beats)
        await asyncio.sleep(0.3)
        assert len(rig.beats) == beats and rig.client.connected
        rig.feeding = True
        await wait_until(lambda: len(rig.beats) > beats)
        assert rig.client.health().healthy


async def test_beat_while_reconnecting_beats_through_an_outage(tmp_path: Path) -> None:
    async with rig_on(str(tmp_path / "gnss"), beat_while_reconnecting=True) as rig:
        await wait_until(lambda: len(rig.received) > 5)
        rig.twin.unplug()
        await wait_until(lambda: not rig.client.connected)
        beats = len(rig.beats)
        await asyncio.sleep(0.3)
        assert len(rig.beats) > beats


def test_the_client_refuses_what_it_cannot_open() -> None:
    with pytest.raises(ValueError, match="baud rate"):
        GnssClient("/dev/ttyUSB0", lambda e, t: None, baudrate_bps=1234)
    with pytest.raises(ValueError, match="resolved"):
        GnssClient("sim://gnss", lambda e, t: None)


# ---- dbw gnss ---------------------------------------------------------------------------
@contextlib.contextmanager
def twin_in_thread(path: str, params: GnssTwinParams, *, feed: bool = True) -> Iterator[GnssTwin]:
    """The CLI runs its own event loop in this thread: the twin is driven from another."""
    twin = GnssTwin(path, params, seed=2)
    stop = threading.Event()

    def drive() -> None:
        while feed and not stop.is_set():
            twin.update(time.monotonic(), *POSE)
            stop.wait(0.005)

    thread = threading.Thread(target=drive, daemon=True)
    thread.start()
    try:
        yield twin
    finally:
        stop.set()
        thread.join()
        twin.close()


def test_probe_reports_a_good_receiver(tmp_path: Path) -> None:
    path = str(tmp_path / "gnss")
    with twin_in_thread(path, GnssTwinParams()):
        result = CliRunner().invoke(gnss, ["probe", path, "--seconds", "1"])
    out = result.output
    assert result.exit_code == 0, out
    for name in ("GGA", "RMC", "VTG", "HDT", "GST"):
        rate = re.search(rf"{name} (\d+\.\d) Hz", out)
        assert rate is not None and 8.5 <= float(rate[1]) <= 11.5, out
    assert "fix: rtk fixed (4)" in out and "satellites: 16, HDOP: 0.7" in out
    assert "sigma (GST): 0.050 m" in out and "heading: present (HDT" in out
    position = re.search(r"position: (\d+\.\d+) N, (\d+\.\d+) W", out)
    assert position is not None
    lat, lon, _ = pymap3d.enu2geodetic(POSE[0], POSE[1], 0.0, 42.4591, -71.2674, 100.0)
    assert float(position[1]) == pytest.approx(float(lat), abs=3e-6)  # 0.05 m noise: ~5e-7°
    assert float(position[2]) == pytest.approx(-float(lon), abs=3e-6)
    assert "rejected lines: none" in out and "link:" not in out
    assert out.rstrip().endswith("verdict: usable for autopilot")


def test_probe_says_why_a_degraded_receiver_is_not_usable(tmp_path: Path) -> None:
    path = str(tmp_path / "gnss")
    params = GnssTwinParams(
        rate_hz=2.0,
        sentences=("GGA", "RMC", "GST"),
        quality=FixQuality.GPS,
        position_noise_m=1.5,
        corrupt_fraction=0.3,
    )
    with twin_in_thread(path, params):
        result = CliRunner().invoke(gnss, ["probe", path, "--seconds", "1.2"])
    out = result.output
    assert result.exit_code == 0, out  # NMEA was heard: the port and baud rate are right
    assert "fix: gps (1)" in out and "heading: absent" in out
    assert "rejected lines: checksum" in out and "last bad line (checksum): $GN" in out
    verdict_line = out.strip().splitlines()[-1]
    assert verdict_line.startswith("verdict: NOT usable for autopilot: ")
    assert "below 5 Hz" in verdict_line and "sigma 1.500 m above 0.1 m" in verdict_line
    assert "no valid true heading" in verdict_line


def test_probe_on_a_missing_port_is_a_clean_error(tmp_path: Path) -> None:
    result = CliRunner().invoke(gnss, ["probe", str(tmp_path / "nothing"), "--seconds", "1"])
    assert result.exit_code == 1
    assert isinstance(result.exception, SystemExit)  # no traceback
    assert "cannot open" in result.output and "No such file" in result.output


def test_probe_on_a_silent_port_finds_no_nmea(tmp_path: Path) -> None:
    path = str(tmp_path / "gnss")
    with twin_in_thread(path, CLEAN, feed=False):
        result = CliRunner().invoke(gnss, ["probe", path, "--seconds", "0.3"])
    assert result.exit_code == 1
    assert "verdict: no NMEA sentence heard in 0.3 s (nothing received)" in result.output


def test_probe_refuses_a_baud_rate_no_receiver_uses() -> None:
    result = CliRunner().invoke(gnss, ["probe", "/dev/null", "--baud", "1234"])
    assert result.exit_code == 2 and "1234 is not one of" in result.output


def test_verdict_rules() -> None:
    def stats(quality: FixQuality, sigma_m: float, hz: float, heading: bool) -> ProbeStats:
        s = ProbeStats()
        gga = GgaFix("GN", 0.0, 1.0, 2.0, quality, 12, 0.8, 10.0, 0.0, None)
        gst = GstError("GN", 0.0, sigma_m, sigma_m, sigma_m, 0.0, sigma_m, sigma_m, sigma_m)
        for k in range(11):
            s.add(gga, k / hz)
            s.add(gst, k / hz)
            s.add(Heading("GN", "HDT", 1.0, valid=heading, mode=None), k / hz)
        return s

    good = stats(FixQuality.RTK_FIXED, 0.02, 10.0, heading=True)
    assert verdict(good, bad_lines=0, seconds=1.0) == []
    assert verdict(good, bad_lines=1, seconds=1.0) == []  # 1 of 34 lines: 3 %
    assert verdict(good, bad_lines=2, seconds=1.0) == [
        "6% of lines damaged (cable, noise or baud rate)"
    ]
    assert verdict(stats(FixQuality.RTK_FIXED, 0.02, 4.0, True), 0, 3.0) == [
        "position at 4.0 Hz, below 5 Hz"
    ]
    assert verdict(stats(FixQuality.RTK_FLOAT, 0.2, 10.0, True), 0, 1.0) == [
        "sigma 0.200 m above 0.1 m"
    ]
    assert verdict(stats(FixQuality.SIMULATION, 0.02, 10.0, False), 0, 1.0) == [
        "fix quality simulation (8)",
        "no valid true heading (HDT or THS)",
    ]
    assert verdict(ProbeStats(), 0, 1.0) == [
        "no GGA: no position",
        "no sigma (GST): the position error is unknown",
        "no valid true heading (HDT or THS)",
    ]


def test_record_writes_every_line_with_its_times(tmp_path: Path) -> None:
    path, output = str(tmp_path / "gnss"), tmp_path / "gnss.log"
    params = dataclasses.replace(CLEAN, corrupt_fraction=0.25, split_fraction=0.5)
    before_s, before_wall = time.monotonic(), dt.datetime.now(dt.UTC)
    with twin_in_thread(path, params) as twin:
        result = CliRunner().invoke(gnss, ["record", path, "-o", str(output), "--seconds", "0.8"])
    assert result.exit_code == 0, result.output
    rows = [line.split(" ", 3) for line in output.read_text().splitlines()]
    data = [row for row in rows if row[0] != "#"]
    assert rows[0][:3] == ["#", "dbw", "gnss"]
    # 0.8 s at 20 Hz, 5 sentences: 80 lines (the start is cut by the client's port opening).
    assert 50 <= len(data) <= twin.synth.lines
    times = [float(row[0]) for row in data]
    assert times == sorted(times) and before_s <= times[0] <= times[-1] <= time.monotonic()
    for k, row in enumerate(data):
        assert before_wall <= dt.datetime.fromisoformat(row[1]) <= dt.datetime.now(dt.UTC)
        status, line = row[2], row[3]
        if (k == 0 and status == "no_start") or (k == len(data) - 1 and status == "partial"):
            continue  # the recording began or ended inside a line
        body, _, checksum = line[1:].partition("*")
        good = line.startswith("$") and int(checksum, 16) == xor_checksum(body)
        assert status == ("ok" if good else "checksum"), row
    statuses = [row[2] for row in data]
    assert statuses.count("checksum") > 0
    assert f"{len(data)} lines in" in result.output and "; checksum" in result.output


def test_line_log_marks_splits_garbage_and_cuts() -> None:
    out = io.StringIO()
    wall = dt.datetime(2024, 6, 1, 12, 0, tzinfo=dt.UTC)
    log = LineLog(out, lambda: wall)
    good = sentence("GPHDT,12.5,T")
    log.feed(good[:5], 1.0)
    log.feed(good[5:] + b"\xff\x01junk\r", 2.0)
    log.feed(b"\n$GPGSV,1,1,00*79\n$GPGGA,12", 3.0)
    log.link(False, "device disconnected (EOF)", 4.0)
    log.link(True, "open", 5.0)
    log.feed(b"$GPHDT,1.0,T*00\r\n$GPVTG,", 6.0)
    log.finish(7.0)
    iso = wall.isoformat()
    assert out.getvalue().splitlines() == [
        f"2.000000 {iso} ok {good.decode().strip()}",
        f"2.000000 {iso} no_start \\xff\\x01junk",
        f"3.000000 {iso} ignored_type $GPGSV,1,1,00*79",
        f"4.000000 {iso} partial $GPGGA,12",
        f"# 4.000000 {iso} link down: device disconnected (EOF)",
        f"# 5.000000 {iso} link up",
        f"6.000000 {iso} checksum $GPHDT,1.0,T*00",
        f"7.000000 {iso} partial $GPVTG,",
    ]
    assert log.statuses == {"ok": 1, "no_start": 1, "ignored_type": 1, "partial": 2, "checksum": 1}


_RUN_CLI = (
    "import importlib.util, sys;"
    "spec = importlib.util.spec_from_file_location('gnss_cli', sys.argv[1]);"
    "cli = sys.modules['gnss_cli'] = importlib.util.module_from_spec(spec);"
    "spec.loader.exec_module(cli);"
    "cli.gnss(sys.argv[2:], prog_name='dbw gnss')"
)


def test_record_ends_cleanly_on_ctrl_c(tmp_path: Path) -> None:
    """In a process of its own (a SIGINT here would end the test session): only the CLI
    module is loaded, not the whole `dbw` group, to keep the start quick."""
    path, output = str(tmp_path / "gnss"), tmp_path / "gnss.log"
    module = Path(__file__).parents[3] / "appliance" / "cli" / "gnss.py"
    with twin_in_thread(path, CLEAN):
        process = subprocess.Popen(
            [sys.executable, "-c", _RUN_CLI, str(module), "record", path, "-o", str(output)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            assert process.stdout is not None
            lines = [process.stdout.readline() for _ in range(1)]
            while "link_open" not in lines[-1] and lines[-1] and len(lines) < 10:
                lines.append(process.stdout.readline())  # until the client's link_open log
            assert "link_open" in lines[-1], lines
            time.sleep(0.3)
            process.send_signal(signal.SIGINT)
            rest, _ = process.communicate(timeout=10)
        finally:
            if process.poll() is None:
                process.kill()
    assert process.returncode == 0, rest
    assert "Traceback" not in rest and rest.strip().startswith("interrupted: ")
    data = [line for line in output.read_text().splitlines() if not line.startswith("#")]
    assert len(data) >= 10
    assert all(line.split(" ", 3)[2] in ("ok", "partial") for line in data)
    assert os.path.getsize(output) > 0


def test_record_to_an_unwritable_file_is_a_clean_error(tmp_path: Path) -> None:
    path = str(tmp_path / "gnss")
    with twin_in_thread(path, CLEAN, feed=False):
        result = CliRunner().invoke(
            gnss, ["record", path, "-o", str(tmp_path / "no" / "such" / "dir.log")]
        )
    assert result.exit_code == 2 and isinstance(result.exception, SystemExit)
    assert "cannot write" in result.output


def test_the_twin_command_drives_a_circle_on_a_pty(tmp_path: Path) -> None:
    path = tmp_path / "gnss"
    received = bytearray()

    def read() -> None:
        deadline_s = time.monotonic() + 5.0
        while not path.exists() and time.monotonic() < deadline_s:
            time.sleep(0.01)
        fd = os.open(path, os.O_RDONLY | os.O_NOCTTY)
        try:
            while time.monotonic() < deadline_s and (chunk := os.read(fd, 4096)):
                received.extend(chunk)
        except OSError:  # EIO: the twin closed its end
            pass
        finally:
            os.close(fd)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    args = ["twin", "--pty-dir", str(tmp_path), "--seconds", "0.6", "--radius-m", "20"]
    result = CliRunner().invoke(gnss, args)
    reader.join(timeout=6.0)
    assert result.exit_code == 0, result.output
    assert not path.exists()  # unplugged at the end
    ggas = [e for e in _parse(bytes(received)) if isinstance(e, GgaFix)]
    assert len(ggas) >= 3
    for gga in ggas:
        assert gga.lat_deg is not None and gga.lon_deg is not None
        east, north, _ = pymap3d.geodetic2enu(
            gga.lat_deg, gga.lon_deg, 100.0, 42.4591, -71.2674, 100.0
        )
        assert math.hypot(east, north) == pytest.approx(20.0, abs=0.3)  # sigma 0.05 m


def _parse(data: bytes) -> list[NmeaEvent]:
    receiver = NmeaReceiver()
    receiver.receive_data(data)
    return list(receiver.events())
