"""SICK's own driver, sick_scan_xd (stock LMS1xx launch), gets through its start-up on the twin.

Every expected telegram here is written out from the published layout (struct.pack, literal
CoLa-A tokens), never produced by the encoder under test, and the CoLa-B answers are read
back the way sick_scan_xd reads them: by byte offset into the framed datagram (its
``parseBinaryDatagram`` for ``sRA fieldNNN``, ``parseBinaryLIDinputstateMsg`` for ``sRA
LIDinputstate``). The start-up sequence is sick_scan_xd's (``sopasCmdVec`` strings and what
``convertAscii2BinaryCmd`` makes of them), with the stock LMS1xx launch parameters: binary
protocol, 50 Hz at 0.5°, no RSSI, field monitoring (30 fields) and its three events on.
"""

from __future__ import annotations

import asyncio
import functools
import operator
import struct
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pytest

from appliance.sim import Pose2D, load_site
from appliance.sim.twins.lms111 import Lms111Twin
from drivers.lms111 import (
    NEED_DATA,
    ColaFramer,
    CommandType,
    Dialect,
    ErrorReply,
    Lms111Connection,
    ProtocolError,
    Reply,
    ScanTelegram,
    Telegram,
    parse_set_scan_config,
)
from drivers.lms111.errors import TruncatedTelegram
from drivers.lms111.twin_device import DeviceModel, PeerState

BOTH = pytest.mark.parametrize("dialect", list(Dialect), ids=lambda d: d.value)
FIELDS = range(30)  # sick_scan_xd: LMS1xx -> "LMS5xx" field logic, 30 fields
NOW_S = 10.0  # device time 10 s after power-up: system counter 10_000_000 µs = 989680h


def xor(payload: bytes) -> int:
    return functools.reduce(operator.xor, payload, 0)


def cola_b(payload: bytes) -> bytes:
    """02 02 02 02, uint32 BE length, payload, XOR of the payload (the listing's framing)."""
    return b"\x02\x02\x02\x02" + struct.pack(">I", len(payload)) + payload + bytes([xor(payload)])


def cola_a(payload: bytes) -> bytes:
    return b"\x02" + payload + b"\x03"


def expected_field_params_b(index: int) -> bytes:
    """Unconfigured field: scale 1.0, offset 0.0, 0.5°/index from -45°, segmented (2),
    number index + 1, no segmented/rectangular/radial/dynamic part, trailer 1, "", 0."""
    return struct.pack(
        ">ffIiBBHHHHHHH", 1.0, 0.0, 5000, -450_000, 2, index + 1, 0, 0, 0, 0, 1, 0, 0
    )


def expected_field_a(index: int) -> bytes:
    return cola_a(
        b"sRA field%03d 3F800000 00000000 1388 FFF92230 2 %X 0 0 0 0 1 0 0" % (index, index + 1)
    )


@dataclass(frozen=True)
class SickField:
    dist_scale: float
    dist_offset: float
    ang_scale: int
    ang_offset: int
    field_type: int
    field_number: int
    points: int
    rectangular: int
    dynamic: int


def read_field_like_sick_scan_xd(datagram: bytes) -> SickField:
    """sick_scan_xd's parseBinaryDatagram: fixed offsets from the start of the frame."""
    assert len(datagram) >= 41, "sick_scan_xd needs at least 41 bytes"
    dist_scale, dist_offset, ang_scale, ang_offset = struct.unpack_from(">ffIi", datagram, 21)
    field_type, field_number, segmented = struct.unpack_from(">BBH", datagram, 37)
    pos, points = 41, 0
    if segmented == 1:
        (points,) = struct.unpack_from(">H", datagram, pos)
        pos += 2 + 6 * points
    (rectangular,) = struct.unpack_from(">H", datagram, pos)
    pos += 2 + (18 if rectangular == 1 else 0)
    pos += 2  # radial field configured, always 0
    (dynamic,) = struct.unpack_from(">H", datagram, pos)
    pos += 2 + (24 if dynamic == 1 else 0)
    assert pos <= len(datagram) - 1, "the parser must not read into the checksum or beyond"
    return SickField(
        dist_scale,
        dist_offset,
        ang_scale,
        ang_offset,
        field_type,
        field_number,
        points,
        rectangular,
        dynamic,
    )


def read_input_state_like_sick_scan_xd(datagram: bytes) -> tuple[int, int, list[int], int]:
    """parseBinaryLIDinputstateMsg: > 36 bytes; version at 26, counter 28, inputs 32..35,
    time state 36, then (only if it is > 0) year, month, day, hour, minute, second, µs."""
    assert len(datagram) > 36
    version, counter = struct.unpack_from(">HI", datagram, 26)
    inputs = list(datagram[32:36])
    (time_state,) = struct.unpack_from(">H", datagram, 36)
    end = 38 + (struct.calcsize(">HBBBBBI") if time_state > 0 else 0)
    assert end == len(datagram) - 1, "nothing between the last field and the checksum"
    return version, counter, inputs, time_state


def _flat_world(
    _: float, angles_rad: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], ...]:
    return np.full(len(angles_rad), 5.0), np.full(len(angles_rad), 0.5)


def device_answer(dialect: Dialect, request: bytes, *, logged_in: bool = False) -> bytes:
    """The twin's device model, sans I/O: the framed request in, the framed answer out."""
    device = DeviceModel(_flat_world, dialect=dialect)
    twin = Lms111Connection(dialect)
    twin.receive_data(request)
    event = twin.next_event()
    assert isinstance(event, Reply), event
    answer = device.handle(event, PeerState(access_level=3 if logged_in else 0), NOW_S)
    if answer.error_code is not None:
        return twin.send_error(answer.error_code)
    assert answer.command is not None
    return twin.send(answer.command)


# ---- 1. sRN field000 .. field029 -------------------------------------------------------
@pytest.mark.parametrize("index", [0, 1, 9, 10, 29])
def test_every_field_is_an_unconfigured_field_sick_scan_xd_can_read(index: int) -> None:
    name = b"field%03d" % index
    datagram = device_answer(Dialect.COLA_B, cola_b(b"sRN " + name))
    assert datagram == cola_b(b"sRA " + name + b" " + expected_field_params_b(index))
    assert len(datagram) == 54
    field = read_field_like_sick_scan_xd(datagram)
    assert field == SickField(1.0, 0.0, 5000, -450_000, 2, index + 1, 0, 0, 0)
    assert device_answer(Dialect.COLA_A, cola_a(b"sRN " + name)) == expected_field_a(index)


@BOTH
@pytest.mark.parametrize("name", [b"field030", b"field999", b"fieldABC", b"field00"])
def test_only_the_30_fields_exist(dialect: Dialect, name: bytes) -> None:
    request = cola_a(b"sRN " + name) if dialect is Dialect.COLA_A else cola_b(b"sRN " + name)
    unknown_variable = cola_a(b"sFA 3") if dialect is Dialect.COLA_A else cola_b(b"sFA\x00\x03")
    assert device_answer(dialect, request) == unknown_variable


# ---- 4. sRN LIDinputstate --------------------------------------------------------------
def test_input_state_has_four_inputs_and_no_time_stamp() -> None:
    datagram = device_answer(Dialect.COLA_B, cola_b(b"sRN LIDinputstate"))
    params = struct.pack(">HI4BH", 0, 10_000_000, 0, 0, 0, 0, 0)
    assert datagram == cola_b(b"sRA LIDinputstate " + params)
    assert read_input_state_like_sick_scan_xd(datagram) == (0, 10_000_000, [0, 0, 0, 0], 0)
    ascii_answer = device_answer(Dialect.COLA_A, cola_a(b"sRN LIDinputstate"))
    assert ascii_answer == cola_a(b"sRA LIDinputstate 0 989680 0 0 0 0 0")


# ---- 3. binary bytes in a complete CoLa-A frame ----------------------------------------
# sick_scan_xd #128: an LMS1xx V1.80.1 answered this (binary parameters, ASCII frame) with 11.
BINARY_SET_SCAN_CONFIG = struct.pack(">IHIii", 5000, 1, 5000, -450_000, 2_250_000)


@pytest.mark.parametrize("logged_in", [True, False])
def test_binary_parameters_in_a_cola_a_frame_are_an_invalid_character(logged_in: bool) -> None:
    request = cola_a(b"sMN mLMPsetscancfg " + BINARY_SET_SCAN_CONFIG)
    assert device_answer(Dialect.COLA_A, request, logged_in=logged_in) == cola_a(b"sFA 11")
    control = cola_a(b"sWN LocationName 3 a\tb")  # one control character is enough
    assert device_answer(Dialect.COLA_A, control, logged_in=logged_in) == cola_a(b"sFA 11")


def test_printable_but_wrong_parameters_still_get_invalid_data() -> None:
    request = cola_a(b"sMN mLMPsetscancfg +5000 +1 +5000 -450000 zz")
    assert device_answer(Dialect.COLA_A, request, logged_in=True) == cola_a(b"sFA 5")


def test_the_same_binary_parameters_are_fine_in_cola_b() -> None:
    request = cola_b(b"sMN mLMPsetscancfg " + BINARY_SET_SCAN_CONFIG)
    answer = device_answer(Dialect.COLA_B, request, logged_in=True)
    assert answer[8:27] == b"sAN mLMPsetscancfg " and answer[27] == 0  # status 0: applied


# ---- 2. a frame cut off by a new STX ---------------------------------------------------
PROBE = cola_b(b"sRN SCdevicestate")  # sick_scan_xd's first request with the stock launch


def test_the_probe_is_what_sick_scan_xd_sends() -> None:
    """sick_scan_xd #419: ``<STX><STX><STX><STX><Len=0017>sRN SCdevicestate CRC:<0x30>``."""
    assert PROBE[4:8] == bytes.fromhex("00000011") and PROBE[-1] == 0x30


def test_a_cola_a_framer_reports_the_probe_as_truncated_telegrams() -> None:
    framer = ColaFramer(Dialect.COLA_A)
    framer.receive_data(PROBE + cola_a(b"sRN SCdevicestate"))
    errors: list[ProtocolError] = []
    telegrams: list[Telegram] = []
    while True:
        try:
            event = framer.next_event()
        except ProtocolError as exc:
            errors.append(exc)
            continue
        if event is NEED_DATA:
            break
        telegrams.append(event)
    # three cut off by the next 02 of the magic, one (the rest) by the request's STX
    assert len(errors) == 4 and all(isinstance(e, TruncatedTelegram) for e in errors)
    assert framer.malformed_telegrams == 4
    assert telegrams == [Telegram(Dialect.COLA_A, b"sRN SCdevicestate")]


def test_the_client_still_counts_a_truncated_telegram_as_malformed() -> None:
    host = Lms111Connection(Dialect.COLA_A)
    host.receive_data(b"\x02sAN Run 1" + cola_a(b"sAN Run 1"))
    with pytest.raises(ProtocolError, match="truncated"):
        host.next_event()
    assert host.malformed_telegrams == 1
    reply = host.next_event()
    assert isinstance(reply, Reply) and reply.fields == ("1",)


# ---- the whole start-up, over TCP, against the twin ------------------------------------
@dataclass(frozen=True)
class Step:
    request: str  # "<type> <name>"
    ascii_params: str = ""  # as sick_scan_xd writes them in CoLa-A
    binary_params: bytes = b""  # as convertAscii2BinaryCmd makes them for CoLa-B

    def wire(self, dialect: Dialect) -> bytes:
        head = self.request.encode()
        if dialect is Dialect.COLA_A:
            return cola_a(head + (b" " + self.ascii_params.encode() if self.ascii_params else b""))
        return cola_b(head + (b" " + self.binary_params if self.binary_params else b""))

    @property
    def answer_kind(self) -> CommandType:
        answers = {"sRN": "sRA", "sWN": "sWA", "sMN": "sAN", "sEN": "sEA"}
        return CommandType(answers[self.request[:3]])

    @property
    def name(self) -> str:
        return self.request[4:]


LOGIN = Step("sMN SetAccessMode", "3 F4724744", b"\x03" + bytes.fromhex("F4724744"))
SWITCH_TO_COLA_B = Step("sWN EIHstCola", "1", b"\x01")
STARTUP = [
    Step("sRN SCdevicestate"),
    LOGIN,
    *(
        Step(f"sRN {name}")
        for name in (
            "DeviceIdent",
            "SerialNumber",
            "FirmwareVersion",
            "SCdevicestate",
            "ODoprh",
            "ODpwrc",
            "LocationName",
            "LMPoutputRange",
        )
    ),
    Step(
        "sWN LMPoutputRange",
        "1 1388 FFF92230 225510",
        struct.pack(">HIii", 1, 5000, -450_000, 2_250_000),
    ),
    Step("sRN LMPoutputRange"),
    *(Step(f"sRN field{index:03d}") for index in FIELDS),
    Step("sRN LIDinputstate"),
    # channel 1, RSSI off, 8 bit, unit 0, no encoder, no position/name/comment, time on, every scan
    Step(
        "sWN LMDscandatacfg",
        "1 0 0 0 0 0 0 0 0 0 1 1",
        bytes([1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1]) + struct.pack(">H", 1),
    ),
    Step("sRN LMDscandatacfg"),
    Step("sMN mLMPsetscancfg", "+5000 +1 +5000 -450000 +2250000", BINARY_SET_SCAN_CONFIG),
    Step("sRN LMPscancfg"),
    Step("sMN LMCstartmeas"),
    Step("sMN Run"),
    *(
        Step(f"sEN {event}", "1", b"\x01")
        for event in ("LMDscandata", "LFErec", "LIDoutputstate", "LIDinputstate")
    ),
]


class SickScanXdHost:
    """The driver's end of the TCP connection: raw request bytes out, typed answers in."""

    def __init__(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, dialect: Dialect
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.connection = Lms111Connection(dialect)

    async def send(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def answer(self) -> Reply | ErrorReply:
        """The next answer; scans (streaming once subscribed) are skipped."""
        while True:
            event = self.connection.next_event()
            if isinstance(event, ScanTelegram):
                continue
            if event is not NEED_DATA:
                return event
            async with asyncio.timeout(5.0):
                chunk = await self.reader.read(65536)
            assert chunk, "the twin closed the connection"
            self.connection.receive_data(chunk)


def check_answer(step: Step, answer: Reply | ErrorReply, dialect: Dialect) -> None:
    assert isinstance(answer, Reply), f"{step.request}: {answer}"
    assert (answer.kind, answer.name) == (step.answer_kind, step.name), step.request
    assert answer.dialect is dialect
    index = int(step.name[5:]) if step.name.startswith("field") else None
    if index is not None and dialect is Dialect.COLA_B:
        assert answer.params == expected_field_params_b(index)
        datagram = cola_b(b"sRA " + step.name.encode() + b" " + answer.params)
        assert read_field_like_sick_scan_xd(datagram).points == 0
    elif index is not None:
        assert cola_a(b"sRA " + step.name.encode() + b" " + answer.params) == expected_field_a(
            index
        )
    if step.name == "LIDinputstate" and step.answer_kind is CommandType.SRA:
        if dialect is Dialect.COLA_B:
            datagram = cola_b(b"sRA LIDinputstate " + answer.params)
            assert read_input_state_like_sick_scan_xd(datagram)[2:] == ([0, 0, 0, 0], 0)
        else:
            assert len(answer.fields) == 7 and answer.fields[2:] == ("0",) * 5
    if step.name == "mLMPsetscancfg":
        assert parse_set_scan_config(answer).status == 0


SCENARIOS = {
    # a CoLa-A LMS111, the driver configured for ASCII after its binary probe went unanswered
    "cola-a-device": (Dialect.COLA_A, Dialect.COLA_A, [PROBE], STARTUP),
    # the stock launch against a CoLa-A LMS111: probe, then switch the device to CoLa-B
    "cola-a-device-switched": (
        Dialect.COLA_A,
        Dialect.COLA_B,
        [PROBE],
        [STARTUP[0], LOGIN, SWITCH_TO_COLA_B, *STARTUP],
    ),
    # a device already in CoLa-B answers the probe itself
    "cola-b-device": (Dialect.COLA_B, Dialect.COLA_B, [], STARTUP),
}


@pytest.mark.parametrize("scenario", list(SCENARIOS))
async def test_sick_scan_xd_start_up_gets_no_sfa(scenario: str) -> None:
    device_dialect, driver_dialect, silent, steps = SCENARIOS[scenario]
    twin = Lms111Twin(
        load_site("launcher"),
        Pose2D(0.0, 0.0, 0.0),
        lambda _: Pose2D(-10.0, 0.0, 0.0),
        dialect=device_dialect,
    )
    await twin.start()
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", twin.port)
        host = SickScanXdHost(reader, writer, device_dialect)
        for data in silent:  # no answer: the next one received belongs to the next request
            await host.send(data)
        dialect = device_dialect
        for step in steps:
            await host.send(step.wire(dialect))
            answer = await host.answer()
            check_answer(step, answer, dialect)
            if step is SWITCH_TO_COLA_B:
                dialect = driver_dialect
                host.connection.switch_dialect(dialect)
        assert twin.stats.truncated_requests == (4 if silent else 0)
        assert host.connection.malformed_telegrams == 0
        writer.close()
    finally:
        await twin.stop()
