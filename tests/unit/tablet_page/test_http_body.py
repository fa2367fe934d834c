"""POST bodies in the page server's sans-I/O reader: only where allowed, only small."""

from __future__ import annotations

import contextlib
from http import HTTPStatus

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.operator_page.http import NEED_DATA, HttpError, Request, RequestReader

BODY = b'{"seq": 7, "held": true}'
POST = (
    b"POST /api/hold HTTP/1.1\r\nHost: 10.0.0.2:8090\r\nContent-Type: application/json\r\n"
    b"Content-Length: " + str(len(BODY)).encode() + b"\r\n\r\n" + BODY
)


def _length(header: bytes) -> bytes:
    """POST with its Content-Length line replaced by ``header`` (none when empty)."""
    line = b"Content-Length: 24\r\n"
    return POST.replace(line, header + b"\r\n" if header else b"")


def _read(data: bytes, chunks: list[int] | None = None, max_body: int = 4096) -> object:
    reader = RequestReader(max_body_bytes=max_body)
    cuts = [*sorted(set(chunks or []) - {0}), len(data)]  # b"" would say closed
    start = 0
    event: object = NEED_DATA
    for cut in cuts:
        reader.receive_data(data[start:cut])
        start = cut
        event = reader.next_event()
        if event is not NEED_DATA:
            return event
    reader.receive_data(b"")
    return reader.next_event()


@given(st.lists(st.integers(0, len(POST)), max_size=8))
def test_a_post_arrives_whole_however_it_is_split(cuts: list[int]) -> None:
    event = _read(POST, cuts)
    assert isinstance(event, Request)
    assert (event.method, event.path, event.body) == ("POST", "/api/hold", BODY)


@pytest.mark.parametrize(
    ("data", "status"),
    [
        (_length(b"Content-Length: 5000"), HTTPStatus.REQUEST_ENTITY_TOO_LARGE),
        (_length(b""), HTTPStatus.LENGTH_REQUIRED),
        (_length(b"Transfer-Encoding: chunked"), HTTPStatus.NOT_IMPLEMENTED),
        (_length(b"Content-Length: 24\r\nContent-Length: 25"), HTTPStatus.BAD_REQUEST),
        (_length(b"Content-Length: -1"), HTTPStatus.BAD_REQUEST),
        (POST[:-5], HTTPStatus.BAD_REQUEST),  # closed mid-body
    ],
)
def test_a_body_too_large_unsized_chunked_or_cut_is_refused(data: bytes, status: int) -> None:
    with pytest.raises(HttpError) as caught:
        _read(data)
    assert caught.value.status == status


def test_a_reader_without_bodies_refuses_post_as_before() -> None:
    with pytest.raises(HttpError) as caught:
        _read(POST, max_body=0)
    assert caught.value.status == HTTPStatus.METHOD_NOT_ALLOWED
    get_with_body = b"GET / HTTP/1.1\r\nHost: a\r\nContent-Length: 3\r\n\r\nabc"
    with pytest.raises(HttpError) as caught:
        _read(get_with_body)
    assert caught.value.status == HTTPStatus.BAD_REQUEST


@given(st.binary(max_size=300))
def test_any_bytes_give_a_request_or_an_http_error(data: bytes) -> None:
    with contextlib.suppress(HttpError):
        _read(data)
