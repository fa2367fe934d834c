"""The twin's device model answers what an LMS111 answers; its server switches dialects."""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import numpy.typing as npt
import pytest

from appliance.sim import Pose2D, load_site
from appliance.sim.twins.lms111 import Lms111Twin
from drivers.lms111 import (
    NEED_DATA,
    Command,
    CommandType,
    Dialect,
    ErrorReply,
    Lms111Connection,
    Reply,
    ScanConfig,
    ScanDataConfig,
    ScanTelegram,
    configure_scan_data,
    parse_device_state,
    parse_device_status,
    parse_output_range,
    parse_scan_config,
    parse_set_scan_config,
    read_device_state,
    read_device_status,
    read_output_range,
    read_scan_config,
    set_access_mode,
    set_cola_dialect,
    set_output_range,
    set_scan_config,
    start_measurement,
    stop_measurement,
    subscribe,
)
from drivers.lms111.session import Lms111LinkError, Lms111Session
from drivers.lms111.twin_device import DeviceModel, PeerState, rssi_digits


def _flat_world(
    _: float, angles_rad: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], ...]:
    return np.full(len(angles_rad), 5.0), np.full(len(angles_rad), 0.5)


class Host:
    """A host talking to a `DeviceModel` through two sans-I/O connections, no sockets."""

    def __init__(self, dialect: Dialect = Dialect.COLA_A) -> None:
        self.device = DeviceModel(_flat_world, dialect=dialect)
        self.host = Lms111Connection(dialect)
        self.twin = Lms111Connection(dialect)
        self.peer = PeerState()
        self.now_s = 10.0

    def ask(self, command: Command) -> Reply | ErrorReply | ScanTelegram:
        self.twin.receive_data(self.host.send(command))
        request = self.twin.next_event()
        assert isinstance(request, Reply)
        answer = self.device.handle(request, self.peer, self.now_s)
        if answer.error_code is not None:
            wire = self.twin.send_error(answer.error_code)
        elif answer.scan is not None:
            wire = self.twin.send_scan(answer.scan, CommandType.SRA)
        else:
            assert answer.command is not None
            wire = self.twin.send(answer.command)
        self.host.receive_data(wire)
        event = self.host.next_event()
        assert event is not NEED_DATA and self.host.next_event() is NEED_DATA
        return event

    def reply(self, command: Command) -> Reply:
        event = self.ask(command)
        assert isinstance(event, Reply), event
        return event

    def error_code(self, command: Command) -> int:
        event = self.ask(command)
        assert isinstance(event, ErrorReply), event
        return event.code


@pytest.mark.parametrize("dialect", list(Dialect), ids=lambda d: d.value)
def test_every_start_up_request_of_the_official_drivers_is_answered(dialect: Dialect) -> None:
    host = Host(dialect)
    for name in (
        "DeviceIdent",
        "FirmwareVersion",
        "SerialNumber",
        "LocationName",
        "SCdevicestate",
        "STlms",
        "LMPscancfg",
        "LMPoutputRange",
        "LMDscandatacfg",
        "ODoprh",
        "ODpwrc",
        "LFErec",
        "LIDoutputstate",
        "LIDinputstate",
        *(f"field{index:03d}" for index in range(30)),  # sick_scan_xd's LMS1xx fields
    ):
        assert host.reply(Command(CommandType.SRN, name)).kind is CommandType.SRA, name
    assert host.reply(set_access_mode()).fields[:1] in (("1",), ())
    for event in ("LFErec", "LIDoutputstate", "LIDinputstate", "LMDscandata"):
        assert host.reply(subscribe(event)).kind is CommandType.SEA
    assert "LMDscandata" in host.peer.subscriptions
    assert host.reply(stop_measurement()).kind is CommandType.SAN
    assert parse_device_status(host.reply(read_device_status())).state == 3  # idle
    assert host.reply(start_measurement()).kind is CommandType.SAN
    polled = host.ask(Command(CommandType.SRN, "LMDscandata"))
    assert isinstance(polled, ScanTelegram) and polled.kind is CommandType.SRA
    assert np.all(polled.scan.ranges_m == 5.0)


def test_refusals_carry_the_sopas_codes_a_device_sends() -> None:
    host = Host()
    assert host.error_code(Command(CommandType.SRN, "NoSuchVariable")) == 0x03
    assert host.error_code(Command(CommandType.SMN, "mNoSuchMethod")) == 0x02
    assert host.error_code(subscribe("NoSuchEvent")) == 0x0F
    assert host.error_code(configure_scan_data(ScanDataConfig())) == 0x0A  # not logged in
    assert host.error_code(start_measurement()) == 0x01  # not logged in
    host.reply(set_access_mode())
    full = set_scan_config(ScanConfig(5000, 5000))
    short = Command(CommandType.SMN, full.name, full.fields[:2])
    assert host.error_code(short) == 0x08  # what an LMS1xx answered (sick_scan_xd #39)
    wrong_password = set_access_mode(3, 0x12345678)
    assert host.reply(wrong_password).fields == ("0",)


@pytest.mark.parametrize(
    ("frequency_hz", "resolution_deg", "status"),
    [(50, 0.5, 0), (25, 0.25, 0), (25, 0.5, 0), (50, 0.25, 2), (35, 0.5, 1), (35, 0.1, 3)],
)
def test_scan_configuration_accepts_only_lms111_modes(
    frequency_hz: float, resolution_deg: float, status: int
) -> None:
    host = Host()
    host.reply(set_access_mode())
    result = parse_set_scan_config(
        host.reply(set_scan_config(ScanConfig.from_si(frequency_hz, resolution_deg)))
    )
    assert result.status == status
    applied = parse_scan_config(host.reply(read_scan_config()))
    assert applied == result.config
    expected_frequency = frequency_hz if status == 0 else 50
    assert applied.scan_frequency_hz == expected_frequency


def test_output_range_reports_half_a_degree_whatever_the_resolution() -> None:
    """The LMS1xx quirk (clearpath LMS1xx #39, #51) a driver must not trust."""
    host = Host()
    host.reply(set_access_mode())
    host.reply(set_scan_config(ScanConfig.from_si(25, 0.25)))
    output = parse_output_range(host.reply(read_output_range()))
    assert output.angular_resolution_deg == 0.5
    host.reply(set_output_range(2500, 0, 1_800_000))  # 0°..180° only: shorter telegrams
    scan = host.device.measure(host.now_s)
    assert scan is not None and len(scan.ranges_m) == 721
    assert scan.angular_step_rad == pytest.approx(math.radians(0.25))


def test_not_ready_and_busy_until_the_device_is_up() -> None:
    host = Host()
    host.device.boot(host.now_s, not_ready_s=1.0)
    assert parse_device_status(host.reply(read_device_status())).state == 5
    assert parse_device_state(host.reply(read_device_state())) == 0  # busy
    assert not host.device.streaming(host.now_s + 0.5)
    host.now_s += 1.0
    assert parse_device_status(host.reply(read_device_status())).measuring
    assert host.device.streaming(host.now_s)


def test_scan_content_follows_the_data_configuration() -> None:
    host = Host()
    host.reply(set_access_mode())
    host.reply(configure_scan_data(ScanDataConfig(remission_16bit=False, time=True)))
    scan = host.device.measure(host.now_s)
    assert scan is not None
    assert [c.name for c in scan.channels_8bit] == ["RSSI1"] and scan.timestamp is not None
    assert scan.timestamp.year == 1970 and scan.intensities is not None
    assert scan.intensities.max() <= 255
    digits = rssi_digits(np.array([0.9, 0.1, 5.0, 0.5]), np.array([1.0, 1.0, 1.0, 0.0]), True)
    assert list(digits) == [900.0, 100.0, 5000.0, 0.0]


async def test_eihstcola_switches_the_device_and_answers_in_the_old_dialect() -> None:
    twin = Lms111Twin(
        load_site("launcher"), Pose2D(0.0, 0.0, 0.0), lambda _: Pose2D(-10.0, 0.0, 0.0)
    )
    await twin.start()
    try:
        session = await Lms111Session.connect("127.0.0.1", twin.port, Dialect.COLA_A)
        await session.request(set_access_mode())
        answer = await session.request(set_cola_dialect(Dialect.COLA_B))
        assert answer.dialect is Dialect.COLA_A
        session.connection.switch_dialect(Dialect.COLA_B)
        status = await session.request(read_device_status())
        assert status.dialect is Dialect.COLA_B and parse_device_status(status).measuring
        await session.close()
        later = await Lms111Session.connect("127.0.0.1", twin.port, Dialect.COLA_B)
        assert parse_device_status(await later.request(read_device_status())).measuring
        await later.close()
        await twin.stop()
        await twin.start()  # a power cycle restores the default dialect
        assert twin.device.dialect is Dialect.COLA_A
    finally:
        await twin.stop()


async def test_run_serves_and_beats_until_cancelled_then_closes_the_port() -> None:
    twin = Lms111Twin(
        load_site("launcher"), Pose2D(0.0, 0.0, 0.0), lambda _: Pose2D(-10.0, 0.0, 0.0)
    )
    beats: list[float] = []
    started_s = time.monotonic()
    task = asyncio.create_task(twin.run(lambda: beats.append(0.0)))
    async with asyncio.timeout(10.0):  # events, not a fixed time: a loaded machine is slow
        while not twin.running:
            await asyncio.sleep(0.005)
        session = await Lms111Session.connect("127.0.0.1", twin.port)
        assert parse_device_status(await session.request(read_device_status())).measuring
        await session.close()
        while len(beats) < 3:
            await asyncio.sleep(0.005)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    elapsed_s = time.monotonic() - started_s
    # one per 20 ms period, on the schedule: never more than the periods that began
    assert 3 <= len(beats) <= elapsed_s / twin.device.period_s + 1
    assert not twin.running
    with pytest.raises(Lms111LinkError, match="failed"):
        await Lms111Session.connect("127.0.0.1", twin.port)
