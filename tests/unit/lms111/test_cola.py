"""Commands, replies and errors: exact bytes from the telegram listing, both dialects."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.lms111 import (
    NEED_DATA,
    SOPAS_ERRORS,
    CommandType,
    DeviceIdent,
    DeviceStatus,
    Dialect,
    ErrorReply,
    Event,
    Lms111Connection,
    ProtocolError,
    Reply,
    ScanConfig,
    ScanDataConfig,
    answer_access_mode,
    answer_device_ident,
    answer_device_state,
    answer_device_status,
    answer_event,
    answer_method,
    answer_output_range,
    answer_scan_config,
    answer_set_scan_config,
    answer_string_variable,
    answer_write,
    configure_scan_data,
    encode_error,
    frame,
    parse_access_mode,
    parse_device_ident,
    parse_device_state,
    parse_device_status,
    parse_event_answer,
    parse_event_request,
    parse_method_status,
    parse_output_range,
    parse_scan_config,
    parse_scan_data_config_request,
    parse_set_access_mode_request,
    parse_set_dialect_request,
    parse_set_scan_config,
    parse_set_scan_config_request,
    parse_string_variable,
    poll_scan,
    read_device_status,
    read_output_range,
    read_scan_config,
    run,
    set_access_mode,
    set_cola_dialect,
    set_output_range,
    set_scan_config,
    start_measurement,
    stop_measurement,
    subscribe,
    subscribe_scans,
)
from tests.unit.lms111 import golden

LMS111_DEFAULT = ScanConfig.from_si(50.0, 0.5, -45.0, 225.0)


def receive(data: bytes, dialect: Dialect = Dialect.COLA_A) -> Event:
    conn = Lms111Connection(dialect)
    conn.receive_data(data)
    event = conn.next_event()
    assert event is not NEED_DATA
    assert conn.next_event() is NEED_DATA
    return event


def receive_reply(data: bytes, dialect: Dialect = Dialect.COLA_A) -> Reply:
    event = receive(data, dialect)
    assert isinstance(event, Reply)
    return event


# --- Requests: the exact bytes of the listing's examples. ---


@pytest.mark.parametrize(
    ("command", "cola_a"),
    [
        (set_access_mode(), b"\x02sMN SetAccessMode 03 F4724744\x03"),
        (
            set_scan_config(LMS111_DEFAULT),
            b"\x02sMN mLMPsetscancfg +5000 +1 +5000 -450000 +2250000\x03",
        ),
        (
            configure_scan_data(ScanDataConfig(remission=False)),
            b"\x02sWN LMDscandatacfg 01 00 0 1 0 00 00 0 0 0 0 +1\x03",
        ),
        (
            configure_scan_data(
                ScanDataConfig(output_channel=2, encoder=1, output_interval=10, remission=False)
            ),
            b"\x02sWN LMDscandatacfg 02 00 0 1 0 01 00 0 0 0 0 +10\x03",
        ),
        (read_scan_config(), b"\x02sRN LMPscancfg\x03"),
        (read_output_range(), b"\x02sRN LMPoutputRange\x03"),
        (
            set_output_range(5000, -450000, 2250000),
            b"\x02sWN LMPoutputRange 1 1388 FFF92230 225510\x03",
        ),
        (start_measurement(), b"\x02sMN LMCstartmeas\x03"),
        (stop_measurement(), b"\x02sMN LMCstopmeas\x03"),
        (run(), b"\x02sMN Run\x03"),
        (subscribe_scans(), b"\x02sEN LMDscandata 1\x03"),
        (subscribe_scans(False), b"\x02sEN LMDscandata 0\x03"),
        (poll_scan(), b"\x02sRN LMDscandata\x03"),
        (read_device_status(), b"\x02sRN STlms\x03"),
        (set_cola_dialect(Dialect.COLA_A), b"\x02sWN EIHstCola 0\x03"),
        (set_cola_dialect(Dialect.COLA_B), b"\x02sWN EIHstCola 1\x03"),
        (subscribe("LIDoutputstate"), b"\x02sEN LIDoutputstate 1\x03"),
    ],
)
def test_cola_a_request_bytes(command: object, cola_a: bytes) -> None:
    assert command.encode(Dialect.COLA_A) == cola_a  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("command", "cola_b"),
    [
        (set_access_mode(), golden.SET_ACCESS_MODE_COLA_B),
        (subscribe_scans(), golden.SEN_LMDSCANDATA_1_COLA_B),
        (poll_scan(), golden.SRN_LMDSCANDATA_COLA_B),
        (run(), golden.SMN_RUN_COLA_B),
        (set_cola_dialect(Dialect.COLA_A), golden.SWN_EIHSTCOLA_0_COLA_B),
        (answer_access_mode(True), golden.SAN_SET_ACCESS_MODE_1_COLA_B),
        (answer_method("Run", 1), golden.SAN_RUN_1_COLA_B),
        (answer_write("EIHstCola"), golden.SWA_EIHSTCOLA_COLA_B),
    ],
)
def test_cola_b_bytes_from_the_listing(command: object, cola_b: bytes) -> None:
    assert command.encode(Dialect.COLA_B) == cola_b  # type: ignore[attr-defined]


def test_cola_b_binary_parameters() -> None:
    payload = set_scan_config(LMS111_DEFAULT).payload(Dialect.COLA_B)
    assert payload == (
        b"sMN mLMPsetscancfg " + bytes.fromhex("00001388000100001388fff9223000225510")
    )
    cfg = configure_scan_data(ScanDataConfig()).payload(Dialect.COLA_B)
    assert cfg == b"sWN LMDscandatacfg " + bytes.fromhex("01000101000000000000000001")


# --- Errors. ---


@pytest.mark.parametrize("code", sorted(SOPAS_ERRORS))
def test_every_sfa_code_decodes_in_both_dialects(code: int) -> None:
    a = receive(b"\x02sFA %X\x03" % code)
    b = receive(
        b"\x02\x02\x02\x02\x00\x00\x00\x05sFA"
        + code.to_bytes(2, "big")
        + bytes([0x73 ^ 0x46 ^ 0x41 ^ (code >> 8) ^ (code & 0xFF)]),
        Dialect.COLA_B,
    )
    assert a == b == ErrorReply(code, SOPAS_ERRORS[code][1])
    assert isinstance(a, ErrorReply) and a.constant == SOPAS_ERRORS[code][0]


def test_listed_sfa_meanings() -> None:
    assert receive(b"\x02sFA 1\x03") == ErrorReply.from_code(1)
    assert "access denied" in ErrorReply.from_code(0x01).meaning
    assert "unknown method" in ErrorReply.from_code(0x02).meaning
    assert "unknown variable" in ErrorReply.from_code(0x03).meaning
    assert "invalid data" in ErrorReply.from_code(0x05).meaning
    assert "underflow" in ErrorReply.from_code(0x08).meaning
    assert "write access denied" in ErrorReply.from_code(0x0A).meaning
    assert "unknown CoLa command" in ErrorReply.from_code(0x0C).meaning
    assert "busy" in ErrorReply.from_code(0x0D).meaning
    assert "invalid CoLa-A character" in ErrorReply.from_code(0x11).meaning
    assert "unknown SOPAS error" in ErrorReply.from_code(0x99).meaning
    assert receive(golden.SFA_0A_COLA_B, Dialect.COLA_B) == ErrorReply.from_code(0x0A)


@pytest.mark.parametrize("dialect", list(Dialect))
def test_encode_error_round_trips(dialect: Dialect) -> None:
    assert receive(encode_error(0x11, dialect), dialect) == ErrorReply.from_code(0x11)


@pytest.mark.parametrize(
    "telegram",
    [
        b"\x02xyz Run\x03",
        b"\x02sAN\x03",
        b"\x02sANRun\x03",
        b"\x02sAN R%n\x03",
        b"\x02sFA zz\x03",
        b"\x02sFA\x03",
        b"\x02\xff\xfe\xfd\x03",
    ],
)
def test_malformed_telegrams_raise_protocol_error(telegram: bytes) -> None:
    conn = Lms111Connection()
    conn.receive_data(telegram + b"\x02sAN Run 1\x03")
    with pytest.raises(ProtocolError):
        conn.next_event()
    assert isinstance(conn.next_event(), Reply)  # the stream goes on


# --- Typed replies (client side), from real CoLa-A answers. ---


def test_access_mode_answers() -> None:
    assert parse_access_mode(receive_reply(b"\x02sAN SetAccessMode 1\x03")) is True
    assert parse_access_mode(receive_reply(b"\x02sAN SetAccessMode 0\x03")) is False
    assert (
        parse_access_mode(receive_reply(golden.SAN_SET_ACCESS_MODE_1_COLA_B, Dialect.COLA_B))
        is True
    )


def test_scan_config_answers() -> None:
    config = parse_scan_config(receive_reply(b"\x02sRA LMPscancfg 1388 1 1388 FFF92230 225510\x03"))
    assert config == LMS111_DEFAULT
    assert (config.scan_frequency_hz, config.angular_resolution_deg) == (50.0, 0.5)
    assert (config.start_angle_deg, config.stop_angle_deg) == (-45.0, 225.0)
    result = parse_set_scan_config(
        receive_reply(b"\x02sAN mLMPsetscancfg 0 1388 1 1388 FFF92230 225510\x03")
    )
    assert result.ok and result.config == LMS111_DEFAULT
    refused = parse_set_scan_config(
        receive_reply(b"\x02sAN mLMPsetscancfg 1 9C4 1 1388 FFF92230 225510\x03")
    )
    assert (refused.ok, refused.meaning, refused.config.scan_frequency_hz) == (
        False,
        "frequency error",
        25.0,
    )
    output = parse_output_range(receive_reply(b"\x02sRA LMPoutputRange 1 1388 FFF92230 225510\x03"))
    assert (output.start_angle_deg, output.stop_angle_deg) == (-45.0, 225.0)


def test_device_status_answer() -> None:
    status = parse_device_status(
        receive_reply(b"\x02sRA STlms 7 0 8 00:34:19 A 01.01.1970 0 0 0\x03")
    )
    assert status == DeviceStatus(7, False, "00:34:19", "01.01.1970", 0, 0, 0)
    assert status.measuring


def test_other_answers() -> None:
    assert parse_method_status(receive_reply(b"\x02sAN LMCstartmeas 0\x03"), "LMCstartmeas") == 0
    assert parse_method_status(receive_reply(b"\x02sAN Run 1\x03"), "Run") == 1
    assert parse_event_answer(receive_reply(b"\x02sEA LMDscandata 1\x03")) is True
    assert parse_device_state(receive_reply(b"\x02sRA SCdevicestate 1\x03")) == 1
    ident = parse_device_ident(
        receive_reply(b"\x02sRA DeviceIdent 10 LMS10x_FieldEval 10 V1.36-21.10.2010\x03")
    )
    assert ident == DeviceIdent("LMS10x_FieldEval", "V1.36-21.10.2010")
    assert (
        parse_string_variable(
            receive_reply(b"\x02sRA LocationName D OutdoorDevice\x03"), "LocationName"
        )
        == "OutdoorDevice"
    )
    version = receive_reply(
        b"\x02\x02\x02\x02\x00\x00\x00\x1asRA FirmwareVersion \x00\x04V5.0r", Dialect.COLA_B
    )
    assert parse_string_variable(version, "FirmwareVersion") == "V5.0"
    generic = receive_reply(b"\x02sSN LFErec 3 1 2 3\x03")
    assert (generic.kind, generic.name, generic.fields) == (
        CommandType.SSN,
        "LFErec",
        ("3", "1", "2", "3"),
    )


def test_typed_parsers_reject_the_wrong_reply() -> None:
    with pytest.raises(ProtocolError):
        parse_access_mode(receive_reply(b"\x02sAN Run 1\x03"))
    with pytest.raises(ProtocolError):
        parse_scan_config(receive_reply(b"\x02sRA LMPscancfg 1388 0\x03"))


# --- The twin's side: requests parsed back, answers round-tripped, both dialects. ---


@pytest.mark.parametrize("dialect", list(Dialect))
def test_twin_reads_requests(dialect: Dialect) -> None:
    def request(command: object) -> Reply:
        return receive_reply(command.encode(dialect), dialect)  # type: ignore[attr-defined]

    assert parse_set_access_mode_request(request(set_access_mode())) == (3, 0xF4724744)
    assert parse_set_scan_config_request(request(set_scan_config(LMS111_DEFAULT))) == (
        LMS111_DEFAULT
    )
    config = ScanDataConfig(output_channel=3, time=True, device_name=True, output_interval=50000)
    assert parse_scan_data_config_request(request(configure_scan_data(config))) == config
    assert parse_event_request(request(subscribe_scans(False))) is False
    assert parse_set_dialect_request(request(set_cola_dialect(Dialect.COLA_B))) is Dialect.COLA_B


@pytest.mark.parametrize("dialect", list(Dialect))
def test_twin_answers_round_trip(dialect: Dialect) -> None:
    def answer(command: object) -> Reply:
        return receive_reply(command.encode(dialect), dialect)  # type: ignore[attr-defined]

    assert parse_access_mode(answer(answer_access_mode(False))) is False
    assert parse_scan_config(answer(answer_scan_config(LMS111_DEFAULT))) == LMS111_DEFAULT
    result = parse_set_scan_config(answer(answer_set_scan_config(2, LMS111_DEFAULT)))
    assert (result.status, result.config) == (2, LMS111_DEFAULT)
    assert parse_output_range(answer(answer_output_range(LMS111_DEFAULT))).start_angle_deg == -45
    status = DeviceStatus(7, True, "12:00:01", "31.12.2025", 1, 0, 1)
    assert parse_device_status(answer(answer_device_status(status))) == status
    assert parse_method_status(answer(answer_method("LMCstopmeas", 0)), "LMCstopmeas") == 0
    assert parse_event_answer(answer(answer_event("LMDscandata", True))) is True
    assert parse_device_state(answer(answer_device_state(2))) == 2
    ident = DeviceIdent("LMS111-10100", "V2.10 with spaces")
    assert parse_device_ident(answer(answer_device_ident(ident))) == ident
    name = answer_string_variable("LocationName", "")
    assert parse_string_variable(answer(name), "LocationName") == ""
    if dialect is Dialect.COLA_A:
        assert answer_scan_config(LMS111_DEFAULT).encode(dialect) == (
            b"\x02sRA LMPscancfg 1388 1 1388 FFF92230 225510\x03"
        )


@pytest.mark.parametrize("dialect", list(Dialect))
def test_encoding_out_of_range_values_raises_protocol_error(dialect: Dialect) -> None:
    with pytest.raises(ProtocolError):
        set_access_mode(256).encode(dialect)
    with pytest.raises(ProtocolError):
        set_access_mode(3, 1 << 32).encode(dialect)
    with pytest.raises(ProtocolError):
        configure_scan_data(ScanDataConfig(output_interval=-1)).encode(dialect)


@settings(max_examples=150, deadline=None)
@given(payload=st.binary(min_size=1, max_size=64), dialect=st.sampled_from(list(Dialect)))
def test_any_payload_types_or_raises_protocol_error(payload: bytes, dialect: Dialect) -> None:
    conn = Lms111Connection(dialect)
    if dialect is Dialect.COLA_A:
        payload = payload.replace(b"\x02", b"").replace(b"\x03", b"") or b"x"
    conn.receive_data(frame(dialect, payload))
    try:
        event = conn.next_event()
    except ProtocolError:
        return
    if isinstance(event, Reply):  # typed helpers must also fail cleanly
        for parser in (parse_access_mode, parse_scan_config, parse_device_status):
            with contextlib.suppress(ProtocolError):
                parser(event)
