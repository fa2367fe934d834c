"""Client and twin, both as `Lms111Connection`, talking through a byte pipe (no sockets)."""

from __future__ import annotations

import numpy as np

from drivers.lms111 import (
    NEED_DATA,
    Dialect,
    ErrorReply,
    Event,
    Lms111Connection,
    ProtocolError,
    Reply,
    ScanConfig,
    ScanTelegram,
    answer_access_mode,
    answer_event,
    answer_set_scan_config,
    answer_write,
    parse_access_mode,
    parse_event_answer,
    parse_set_access_mode_request,
    parse_set_dialect_request,
    parse_set_scan_config,
    parse_set_scan_config_request,
    scan_from_ranges,
    set_access_mode,
    set_cola_dialect,
    set_scan_config,
    subscribe_scans,
)


def deliver(data: bytes, to: Lms111Connection, now_s: float = 0.0) -> list[Event]:
    """Feed ``data`` in awkward 7-byte pieces and drain, as a TCP reader loop would."""
    events: list[Event] = []
    for i in range(0, len(data), 7):
        to.receive_data(data[i : i + 7])
        while True:
            try:
                event = to.next_event(host_receive_time_s=now_s)
            except ProtocolError:
                continue
            if event is NEED_DATA:
                break
            events.append(event)
    return events


def one_reply(data: bytes, to: Lms111Connection) -> Reply:
    (event,) = deliver(data, to)
    assert isinstance(event, Reply)
    return event


def test_login_configure_switch_to_cola_b_and_stream() -> None:
    client, twin = Lms111Connection(), Lms111Connection()

    request = one_reply(client.send(set_access_mode()), twin)
    assert parse_set_access_mode_request(request) == (3, 0xF4724744)
    assert parse_access_mode(one_reply(twin.send(answer_access_mode(True)), client))

    wanted = ScanConfig.from_si(50.0, 0.5)
    request = one_reply(client.send(set_scan_config(wanted)), twin)
    applied = parse_set_scan_config_request(request)
    result = parse_set_scan_config(one_reply(twin.send(answer_set_scan_config(0, applied)), client))
    assert result.ok and result.config == wanted

    request = one_reply(client.send(set_cola_dialect(Dialect.COLA_B)), twin)
    new_dialect = parse_set_dialect_request(request)
    answer = twin.send(answer_write("EIHstCola"))  # still in CoLa-A
    twin.switch_dialect(new_dialect)
    assert one_reply(answer, client).name == "EIHstCola"
    client.switch_dialect(Dialect.COLA_B)

    one_reply(client.send(subscribe_scans()), twin)
    assert parse_event_answer(one_reply(twin.send(answer_event("LMDscandata", True)), client))

    ranges = np.linspace(0.5, 19.5, 1081)
    scan = scan_from_ranges(ranges, angular_step_deg=0.25, intensities=np.full(1081, 120))
    wire = twin.send_scan(scan) + twin.send_error(0x0D)
    events = deliver(wire, client, now_s=42.0)
    assert isinstance(events[0], ScanTelegram)
    assert events[0].scan.host_receive_time_s == 42.0
    np.testing.assert_allclose(events[0].scan.ranges_m, ranges, atol=5e-4)
    assert events[1] == ErrorReply.from_code(0x0D)
    assert client.garbage_bytes == client.malformed_telegrams == 0


def test_a_corrupted_scan_is_counted_and_the_next_one_arrives() -> None:
    twin, client = Lms111Connection(Dialect.COLA_B), Lms111Connection(Dialect.COLA_B)
    scan = scan_from_ranges(np.full(541, 3.0))
    good = twin.send_scan(scan)
    bad = bytearray(good)
    bad[100] ^= 0xFF
    events = deliver(b"noise" + bytes(bad) + good, client)
    assert [type(e) for e in events] == [ScanTelegram]
    assert client.malformed_telegrams == 1
    assert client.garbage_bytes == 5
