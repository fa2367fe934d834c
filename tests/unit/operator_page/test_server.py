"""The operator page's HTTP: the sans-I/O reader against hostile bytes, and the asyncio
shell on a real loopback socket against hostile, slow and too many clients.

The reader must turn any bytes into a request, a clean close, or an ``HttpError`` and
nothing else, whether the bytes come whole or one at a time. The shell must answer every
connection with a 4xx (or 505) or close it cleanly, within its deadline, and keep serving
the next client; it never lets a client reach a file, and refuses to listen beyond
loopback unless told to.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
from collections.abc import AsyncIterator, Callable
from http import HTTPStatus
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.operator_page import OperatorPage, scans_document
from appliance.operator_page.http import (
    MAX_HEAD_BYTES,
    NEED_DATA,
    ConnectionClosed,
    HttpError,
    Request,
    RequestReader,
    error_response,
)
from appliance.operator_page.scans import decimate
from appliance.operator_page.server import host_header_name, is_loopback, json_bytes, page_csp
from appliance.topics import TopicRegistry
from drivers.geometry import Pose2D
from drivers.lms111.mounted import MountedScan
from drivers.lms111.scan import scan_from_ranges

GET = b"GET /status.json HTTP/1.1\r\nHost: 127.0.0.1:8080\r\n\r\n"
CLIENT_WAIT_S = 5.0  # generous: how long a test waits for an answer that must come


class Beats:
    def __init__(self) -> None:
        self.count = 0

    def beat(self) -> None:
        self.count += 1


def fake_status() -> dict[str, Any]:
    return {"mode": "ready", "engage_blockers": [], "inputs": {"scan.left": {"age_s": 0.01}}}


# ---------------------------------------------------------------- the reader (no I/O)


def read_all(data: bytes, chunk: int | None = None) -> Request | ConnectionClosed:
    """Feed ``data`` (whole, or ``chunk`` bytes at a time) then end of stream."""
    reader = RequestReader()
    pieces = [data] if chunk is None else [data[i : i + chunk] for i in range(0, len(data), chunk)]
    for piece in [*pieces, b""]:
        reader.receive_data(piece)
        event = reader.next_event()
        if event is not NEED_DATA:
            assert isinstance(event, Request | ConnectionClosed)
            return event
    raise AssertionError("NEED_DATA after end of stream")


def test_a_plain_get_is_a_request() -> None:
    request = read_all(b"GET /status.json?x=1 HTTP/1.1\r\nHost: localhost\r\nAccept: */*\r\n\r\n")
    assert isinstance(request, Request)
    assert (request.method, request.path, request.query) == ("GET", "/status.json", "x=1")
    assert request.header("host") == "localhost"


@pytest.mark.parametrize("chunk", [None, 1, 7])
def test_the_request_is_the_same_whole_or_byte_by_byte(chunk: int | None) -> None:
    assert read_all(GET, chunk) == read_all(GET)


def test_nothing_then_end_of_stream_is_a_clean_close() -> None:
    assert read_all(b"") == ConnectionClosed()


@pytest.mark.parametrize(
    ("data", "status"),
    [
        (b"POST / HTTP/1.1\r\nHost: localhost\r\nContent-Length: 2\r\n\r\nhi", 405),
        (b"DELETE /status.json HTTP/1.1\r\nHost: localhost\r\n\r\n", 405),
        (b"GET / HTTP/2.0\r\nHost: localhost\r\n\r\n", 505),
        (b"GET / HTTP/1.1\r\n\r\n", 400),  # no Host
        (b"GET / HTTP/1.1\r\nHost: a\r\nHost: b\r\n\r\n", 400),
        (b"GET http://evil/ HTTP/1.1\r\nHost: a\r\n\r\n", 400),
        (b"GET / HTTP/1.1\r\nHost: a\r\n folded: value\r\n\r\n", 400),
        (b"GET / HTTP/1.1\r\nHost: a\r\nX: \x00\r\n\r\n", 400),
        (b"GET / HTTP/1.1\r\nHost: a\r\nContent-Length: 5\r\n\r\nhello", 400),
        (b"GET / HTTP/1.1\r\nHost: a\r\nTransfer-Encoding: chunked\r\n\r\n", 400),
        (b"GET /\xff HTTP/1.1\r\nHost: a\r\n\r\n", 400),
        (b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n", 400),  # TLS hello
        (b"GET / HTTP/1.1\r\nHost: a\r\n", 400),  # closed mid-head
    ],
)
def test_bad_requests_raise_http_error_with_their_status(data: bytes, status: int) -> None:
    with pytest.raises(HttpError) as caught:
        read_all(data)
    assert caught.value.status == status


def test_a_head_longer_than_the_limit_is_431_whole_or_streamed() -> None:
    long_header = b"GET / HTTP/1.1\r\nHost: a\r\nX: " + b"a" * MAX_HEAD_BYTES + b"\r\n\r\n"
    for chunk in (None, 1000):
        with pytest.raises(HttpError) as caught:
            read_all(long_header, chunk)
        assert caught.value.status == 431
    # Never terminated: the reader stops at the limit instead of buffering forever.
    reader = RequestReader()
    for _ in range(100):
        reader.receive_data(b"a" * 1000)
        if len(reader._buffer) > MAX_HEAD_BYTES:
            break
    with pytest.raises(HttpError):
        reader.next_event()
    assert len(reader._buffer) <= MAX_HEAD_BYTES + 4


def test_more_than_100_headers_is_431() -> None:
    headers = b"".join(b"X-%d: 1\r\n" % i for i in range(101))
    with pytest.raises(HttpError) as caught:
        read_all(b"GET / HTTP/1.1\r\nHost: a\r\n" + headers + b"\r\n")
    assert caught.value.status == 431


def test_a_405_says_which_methods_are_allowed() -> None:
    response = error_response(HttpError(HTTPStatus.METHOD_NOT_ALLOWED, "POST not allowed"))
    assert response.startswith(b"HTTP/1.1 405 Method Not Allowed\r\n")
    assert b"\r\nAllow: GET, HEAD\r\n" in response


# Requests that look almost right: the reader's branches, not only random noise.
_request_like = st.lists(
    st.sampled_from(
        [
            b"GET",
            b"HEAD",
            b"POST",
            b" ",
            b"/",
            b"/status.json",
            b"/../",
            b"?",
            b"HTTP/1.1",
            b"HTTP/1.0",
            b"HTTP/9.9",
            b"\r\n",
            b"\n",
            b"\r",
            b"Host:",
            b"localhost",
            b":",
            b"Content-Length: 1",
            b"\x00",
            b"\xff",
            b"\t",
            b"a" * 300,
        ]
    ),
    max_size=60,
).map(b"".join)
any_bytes = st.one_of(st.binary(max_size=3000), _request_like)


@given(data=any_bytes, chunk=st.sampled_from([None, 1, 3, 64]))
def test_any_bytes_parse_or_raise_http_error_never_anything_else(
    data: bytes, chunk: int | None
) -> None:
    status = 0
    try:
        event = read_all(data, chunk)
    except HttpError as error:
        status = error.status
    else:
        assert isinstance(event, Request | ConnectionClosed)
    assert status == 0 or 400 <= status < 500 or status == 505


# ---------------------------------------------------------------- the asyncio shell


@contextlib.asynccontextmanager
async def serving(
    status: Callable[[], dict[str, Any]] = fake_status,
    scans: Callable[[], dict[str, Any]] | None = None,
    **kwargs: Any,
) -> AsyncIterator[OperatorPage]:
    page = OperatorPage(status, scans, "127.0.0.1", 0, **kwargs)
    beats = Beats()
    task = asyncio.ensure_future(page.run(beats))
    try:
        async with asyncio.timeout(CLIENT_WAIT_S):
            while page.bound_port is None:
                await asyncio.sleep(0.005)
        assert beats.count >= 1  # beat once listening
        yield page
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def exchange(port: int, data: bytes, *, half_close: bool = True) -> bytes:
    """Send ``data``, say we are done, and read until the server closes."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(data)
        if half_close:
            writer.write_eof()
        async with asyncio.timeout(CLIENT_WAIT_S):
            return await reader.read()
    except ConnectionResetError:
        return b""  # cut off (a deadline passed with our bytes unread): a close, too
    finally:
        writer.close()


def split_response(raw: bytes) -> tuple[int, dict[str, str], bytes]:
    head, _, body = raw.partition(b"\r\n\r\n")
    lines = head.decode("ascii").split("\r\n")
    headers = dict(line.split(": ", 1) for line in lines[1:])
    return int(lines[0].split(" ")[1]), {k.lower(): v for k, v in headers.items()}, body


async def get(port: int, path: str, method: str = "GET", host: str = "127.0.0.1") -> bytes:
    return await exchange(port, f"{method} {path} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())


async def test_the_page_and_the_status_with_their_headers() -> None:
    async with serving() as page:
        assert page.bound_port is not None
        status, headers, body = split_response(await get(page.bound_port, "/"))
        assert status == 200 and body == page.page and b"<script>" in body
        assert headers["content-type"].startswith("text/html")
        assert headers["cache-control"] == "no-store"
        assert headers["x-content-type-options"] == "nosniff"
        assert headers["content-security-policy"].startswith("default-src 'self'")
        assert headers["connection"] == "close"
        status, headers, body = split_response(await get(page.bound_port, "/status.json"))
        assert status == 200 and headers["content-type"] == "application/json"
        assert json.loads(body) == fake_status()
        status, head_headers, body = split_response(await get(page.bound_port, "/", "HEAD"))
        assert status == 200 and body == b""
        assert head_headers["content-length"] == str(len(page.page))


def test_the_shipped_page_runs_only_its_own_inline_script_and_style() -> None:
    page = OperatorPage(fake_status, None)
    csp = page_csp(page.page)
    assert csp.startswith("default-src 'self'; script-src 'sha256-")
    assert "'unsafe-inline'" not in csp and "style-src 'sha256-" in csp
    assert b"http://" not in page.page and b"https://" not in page.page  # no CDN, no network


async def test_status_with_non_finite_numbers_is_still_json_a_browser_parses() -> None:
    doc = {"age": math.inf, "nested": [math.nan, 1.5], "odd": object()}
    async with serving(lambda: doc) as page:
        assert page.bound_port is not None
        _, _, body = split_response(await get(page.bound_port, "/status.json"))
        parsed = json.loads(body)  # strict: Infinity or NaN would not parse in a browser
        assert parsed["age"] is None and parsed["nested"] == [None, 1.5]
        assert isinstance(parsed["odd"], str)
    assert b"Infinity" not in json_bytes({"x": -math.inf})


@pytest.mark.parametrize(
    "path",
    [
        "/../../etc/passwd",
        "/%2e%2e/%2e%2e/etc/passwd",
        "/static/index.html",
        "/index.html/../status.json",
        "//etc/passwd",
        "/status.json/",
        "/favicon.ico",
    ],
)
async def test_anything_but_the_three_paths_is_404(path: str) -> None:
    async with serving() as page:
        assert page.bound_port is not None
        status, _, body = split_response(await get(page.bound_port, path))
        assert status == 404 and b"root:" not in body


async def test_scans_404_without_a_source_and_json_with_one() -> None:
    async with serving() as page:
        assert page.bound_port is not None
        assert split_response(await get(page.bound_port, "/scans.json"))[0] == 404
    scans = {"frame": "vehicle", "scans": {"left": {"points_m": [[1.0, 2.0]]}}}
    async with serving(scans=lambda: scans) as page:
        assert page.bound_port is not None
        status, _, body = split_response(await get(page.bound_port, "/scans.json"))
        assert status == 200 and json.loads(body) == scans


async def test_post_is_405_and_a_foreign_host_is_421() -> None:
    async with serving() as page:
        assert page.bound_port is not None
        status, headers, _ = split_response(await get(page.bound_port, "/status.json", "POST"))
        assert status == 405 and headers["allow"] == "GET, HEAD"
        # DNS rebinding: a page of evil.example whose name now points at 127.0.0.1.
        raw = await get(page.bound_port, "/status.json", host="evil.example:8080")
        assert split_response(raw)[0] == 421
        for host in ("localhost:8080", "[::1]:8080", "127.0.0.1"):
            assert split_response(await get(page.bound_port, "/", host=host))[0] == 200


async def test_oversized_headers_are_refused_and_the_server_goes_on() -> None:
    async with serving() as page:
        assert page.bound_port is not None
        huge = b"GET / HTTP/1.1\r\nHost: a\r\nCookie: " + b"c" * 20_000 + b"\r\n\r\n"
        assert split_response(await exchange(page.bound_port, huge))[0] in (400, 431)
        many = b"".join(b"X-%d: 1\r\n" % i for i in range(150))
        raw = await exchange(page.bound_port, b"GET / HTTP/1.1\r\nHost: a\r\n" + many + b"\r\n")
        assert split_response(raw)[0] == 431
        assert split_response(await get(page.bound_port, "/status.json"))[0] == 200


async def test_a_failing_status_source_is_a_500_not_a_dead_server() -> None:
    calls = 0

    def flaky() -> dict[str, Any]:
        nonlocal calls
        calls += 1
        if calls == 1:
            raise RuntimeError("core not ready")
        return fake_status()

    async with serving(flaky) as page:
        assert page.bound_port is not None
        assert split_response(await get(page.bound_port, "/status.json"))[0] == 500
        assert split_response(await get(page.bound_port, "/status.json"))[0] == 200


async def test_a_slow_client_is_cut_off_and_blocks_no_one() -> None:
    async with serving(request_timeout_s=0.5) as page:
        assert page.bound_port is not None
        reader, writer = await asyncio.open_connection("127.0.0.1", page.bound_port)
        writer.write(b"GET / HTTP/1.1\r\nHo")  # and then nothing, for ever
        # Meanwhile others are served.
        assert split_response(await get(page.bound_port, "/status.json"))[0] == 200
        async with asyncio.timeout(CLIENT_WAIT_S):
            with contextlib.suppress(ConnectionError):
                assert await reader.read() == b""  # cut off: no answer, the connection ends
        writer.close()
        assert page.connection_count == 0


async def test_a_client_that_never_reads_its_answer_is_cut_off() -> None:
    big = {"blob": "x" * 8_000_000}  # far more than the socket buffers hold
    async with serving(lambda: big, request_timeout_s=0.5) as page:
        assert page.bound_port is not None
        _, writer = await asyncio.open_connection("127.0.0.1", page.bound_port)
        writer.write(GET)
        await asyncio.sleep(0.05)
        async with asyncio.timeout(CLIENT_WAIT_S):
            while page.connection_count:
                await asyncio.sleep(0.02)
        assert split_response(await get(page.bound_port, "/"))[0] == 200
        writer.close()


async def test_more_connections_than_allowed_get_503() -> None:
    async with serving(max_connections=3) as page:
        assert page.bound_port is not None
        held = [await asyncio.open_connection("127.0.0.1", page.bound_port) for _ in range(3)]
        async with asyncio.timeout(CLIENT_WAIT_S):
            while page.connection_count < 3:
                await asyncio.sleep(0.005)
        status, _, _ = split_response(await get(page.bound_port, "/status.json"))
        assert status == 503 and page.refused == 1
        for _, writer in held:
            writer.close()
        async with asyncio.timeout(CLIENT_WAIT_S):
            while page.connection_count:
                await asyncio.sleep(0.005)
        assert split_response(await get(page.bound_port, "/status.json"))[0] == 200


async def test_stopping_hangs_up_and_frees_the_port() -> None:
    async with serving() as page:
        port = page.bound_port
        assert port is not None
        idle = await asyncio.open_connection("127.0.0.1", port)
        await asyncio.sleep(0.05)
    assert page.bound_port is None and page.connection_count == 0
    with pytest.raises(ConnectionError):
        await asyncio.open_connection("127.0.0.1", port)
    idle[1].close()


@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(data=any_bytes, half_close=st.booleans())
def test_any_bytes_over_a_socket_get_4xx_or_a_clean_close_never_a_hang(
    data: bytes, half_close: bool
) -> None:
    async def scenario() -> None:
        async with serving(request_timeout_s=0.3) as page:
            assert page.bound_port is not None
            raw = await exchange(page.bound_port, data, half_close=half_close)
            if raw:  # an answer: a 4xx or a 505, never a 5xx crash
                status = int(raw.split(b" ", 2)[1])
                if status == 200:  # only where the bytes happened to be a valid request
                    assert isinstance(read_all(data), Request)
                else:
                    assert 400 <= status < 500 or status == 505
            # And the server still answers the next client.
            assert split_response(await get(page.bound_port, "/status.json"))[0] == 200

    asyncio.run(scenario())


# ---------------------------------------------------------------- binding


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.1.20", "10.0.0.1", "vehicle.local"])
def test_a_non_loopback_host_is_refused_unless_the_vehicle_file_allows_it(host: str) -> None:
    with pytest.raises(ValueError, match="not a loopback address"):
        OperatorPage(fake_status, None, host=host)
    page = OperatorPage(fake_status, None, host=host, allow_non_loopback=True)
    assert not page.check_host_header


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "::1", "localhost"])
def test_loopback_hosts_are_accepted(host: str) -> None:
    assert OperatorPage(fake_status, None, host=host).check_host_header


def test_host_header_names() -> None:
    assert host_header_name("[::1]:8080") == "::1"
    assert host_header_name("localhost:80") == "localhost"
    assert host_header_name("127.0.0.1") == "127.0.0.1"
    assert is_loopback("127.1.2.3") and not is_loopback("evil.example")


# ---------------------------------------------------------------- the last scans


def test_scans_are_thinned_to_360_points_in_the_vehicle_frame() -> None:
    ranges = np.full(541, 5.0)
    ranges[::10] = 0.0  # beams without echo are left out
    mount = Pose2D(3.0, 1.0, math.radians(45.0))
    scan = MountedScan(scan_from_ranges(ranges), "left", mount, 10.0, 0)
    topics = TopicRegistry()
    topics.get("scan.left").publish(scan, 10.0)
    topics.get("board.steering").publish(object(), 10.0)
    doc = scans_document(topics, now_s=10.25)
    assert doc["frame"] == "vehicle" and list(doc["scans"]) == ["left"]
    left = doc["scans"]["left"]
    assert left["age_s"] == pytest.approx(0.25)
    points = np.array(left["points_m"])
    assert 0 < len(points) <= 360
    # Every point is 5 m from the scanner, in the vehicle frame.
    distances = np.hypot(points[:, 0] - mount.x_m, points[:, 1] - mount.y_m)
    np.testing.assert_allclose(distances, 5.0, atol=2e-3)
    json.dumps(doc, allow_nan=False)


def test_decimate_keeps_order_and_bound() -> None:
    points = np.arange(2000, dtype=np.float64).reshape(1000, 2)
    thinned = decimate(points, 360)
    assert len(thinned) <= 360 and (np.diff(thinned[:, 0]) > 0).all()
    assert len(decimate(points[:10], 360)) == 10
