"""The operator page's HTTP/1.1, without I/O: request heads in, typed requests out,
responses as bytes.

Only what a small page needs: GET and HEAD, and POST with a small body for a reader
that allows one (``max_body_bytes``: the tablet page's requests), one request per
connection (every response says ``Connection: close``, so a browser holds no idle
connection that would count against the server's small connection limit). The head is
bounded in bytes and header lines, a body by its Content-Length (chunked bodies are
refused); anything that is not a plain, small request raises :class:`HttpError`, which
carries the status to answer with, and nothing else.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import Enum
from http import HTTPStatus
from typing import Final

MAX_HEAD_BYTES: Final = 8 * 1024
MAX_HEADERS: Final = 100
ALLOWED_METHODS: Final = ("GET", "HEAD")
# RFC 9110 token characters: what a method or a header name may be made of.
_TOKEN: Final = re.compile(rb"[!#$%&'*+\-.^_`|~0-9A-Za-z]+")
# A request target in origin form: printable ASCII without spaces, starting with "/".
_ORIGIN_FORM: Final = re.compile(rb"/[!-~]*")
_VERSION: Final = re.compile(rb"HTTP/1\.[01]")
_ANY_VERSION: Final = re.compile(rb"HTTP/[0-9]\.[0-9]")
# Field values: visible ASCII, spaces and tabs (obs-text, bytes >= 0x80, is refused).
_FIELD_VALUE: Final = re.compile(rb"[\t -~]*")
# The empty line that ends the head; bare LF line endings are tolerated, as h11 does.
_HEAD_END: Final = re.compile(rb"\r?\n\r?\n")

# Headers every response carries: nothing cached, nothing sniffed, nothing framed.
SECURITY_HEADERS: Final[tuple[tuple[str, str], ...]] = (
    ("Cache-Control", "no-store"),
    ("X-Content-Type-Options", "nosniff"),
    ("X-Frame-Options", "DENY"),
    ("Referrer-Policy", "no-referrer"),
)
DEFAULT_CSP: Final = "default-src 'self'"


class HttpError(Exception):
    """A request the server will not serve; ``status`` is the answer, ``reason`` why."""

    def __init__(self, status: HTTPStatus, reason: str) -> None:
        super().__init__(f"{int(status)} {status.phrase}: {reason}")
        self.status = status
        self.reason = reason


class NeedData(Enum):
    NEED_DATA = "need data"


NEED_DATA: Final = NeedData.NEED_DATA


@dataclass(frozen=True)
class ConnectionClosed:
    """The client closed the connection before sending anything: no answer is owed."""


@dataclass(frozen=True)
class Request:
    method: str
    path: str  # the target without its query string
    query: str
    version: str  # "HTTP/1.0" or "HTTP/1.1"
    headers: tuple[tuple[str, str], ...]  # names lower-cased, in the order received
    body: bytes = b""  # a POST's, when the reader allows bodies

    def header(self, name: str) -> str | None:
        """The value of the one header ``name`` (lower case), None if absent."""
        return next((value for key, value in self.headers if key == name), None)


Event = Request | ConnectionClosed


class RequestReader:
    """Bytes of one connection in; one :class:`Request` (or a clean close) out.

    ``receive_data(b"")`` says the client closed its side. ``next_event`` returns
    ``NEED_DATA`` until the head is complete, then the request; it raises
    :class:`HttpError` for anything malformed or too large, never another exception.
    """

    def __init__(
        self,
        max_head_bytes: int = MAX_HEAD_BYTES,
        max_headers: int = MAX_HEADERS,
        max_body_bytes: int = 0,
    ):
        if max_head_bytes < 64 or max_headers < 1 or not 0 <= max_body_bytes <= 1 << 20:
            raise ValueError(
                "max_head_bytes must be at least 64, max_headers at least 1 and "
                "max_body_bytes within [0, 1 MiB]"
            )
        self.max_head_bytes = max_head_bytes
        self.max_headers = max_headers
        self.max_body_bytes = max_body_bytes
        self._buffer = bytearray()
        self._closed = False
        self._done = False

    def receive_data(self, data: bytes) -> None:
        if self._done:
            return  # one request per connection: whatever follows is ignored
        if not data:
            self._closed = True
            return
        # Keep at most one byte past the limit: enough to know the limit was passed.
        room = self.max_head_bytes + self.max_body_bytes + 4 - len(self._buffer)
        self._buffer += data[: max(room, 0)]

    def next_event(self) -> Event | NeedData:
        if self._done:
            raise HttpError(HTTPStatus.BAD_REQUEST, "one request per connection")
        buffer = bytes(self._buffer).lstrip(b"\r\n")  # RFC 9112 2.2: empty lines first
        end = _HEAD_END.search(buffer, 0, self.max_head_bytes + 4)
        if end is None or end.end() > self.max_head_bytes:
            if len(buffer) > self.max_head_bytes or end is not None:
                self._done = True
                raise HttpError(
                    HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE,
                    f"request head longer than {self.max_head_bytes} bytes",
                )
            if self._closed:
                self._done = True
                if not buffer:
                    return ConnectionClosed()
                raise HttpError(HTTPStatus.BAD_REQUEST, "connection closed mid-request")
            return NEED_DATA
        request = parse_head(buffer[: end.start()], self.max_headers, self.max_body_bytes > 0)
        if request.method != "POST":
            self._done = True
            return request
        length = _body_length(request, self.max_body_bytes)
        body = buffer[end.end() : end.end() + length]
        if len(body) < length:
            if self._closed:
                self._done = True
                raise HttpError(HTTPStatus.BAD_REQUEST, "connection closed mid-body")
            return NEED_DATA
        self._done = True
        return Request(
            request.method, request.path, request.query, request.version, request.headers, body
        )


def _body_length(request: Request, max_body_bytes: int) -> int:
    if request.header("transfer-encoding") is not None:
        raise HttpError(HTTPStatus.NOT_IMPLEMENTED, "chunked bodies are not taken: Content-Length")
    lengths = [value for name, value in request.headers if name == "content-length"]
    if not lengths:
        raise HttpError(HTTPStatus.LENGTH_REQUIRED, "a POST needs a Content-Length")
    if len(set(lengths)) != 1 or not lengths[0].isdigit() or len(lengths[0]) > 9:
        raise HttpError(HTTPStatus.BAD_REQUEST, "malformed Content-Length")
    length = int(lengths[0])
    if length > max_body_bytes:
        raise HttpError(
            HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"body of {length} bytes, at most {max_body_bytes}"
        )
    return length


def parse_head(head: bytes, max_headers: int = MAX_HEADERS, post: bool = False) -> Request:
    """The request line and header lines (without the final empty line) as a request;
    ``post``: a POST is allowed (its body is the reader's to take)."""
    lines = head.replace(b"\r\n", b"\n").split(b"\n")
    method, target, version = _request_line(lines[0])
    if len(lines) - 1 > max_headers:
        raise HttpError(
            HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE,
            f"{len(lines) - 1} header lines, at most {max_headers}",
        )
    allowed = (*ALLOWED_METHODS, "POST") if post else ALLOWED_METHODS
    if method not in allowed:
        raise HttpError(
            HTTPStatus.METHOD_NOT_ALLOWED, f"{method} not allowed: {', '.join(allowed)}"
        )
    headers = tuple(_header(line) for line in lines[1:])
    hosts = [value for name, value in headers if name == "host"]
    if len(hosts) > 1 or (version == "HTTP/1.1" and not hosts):
        raise HttpError(HTTPStatus.BAD_REQUEST, "HTTP/1.1 needs exactly one Host header")
    path, _, query = target.partition("?")
    if method != "POST" and any(
        name in ("content-length", "transfer-encoding") for name, _ in headers
    ):
        length = next((v for n, v in headers if n == "content-length"), None)
        if length is None or length.strip() != "0":
            raise HttpError(HTTPStatus.BAD_REQUEST, "a GET or HEAD request has no body")
    return Request(method, path, query, version, headers)


def _request_line(line: bytes) -> tuple[str, str, str]:
    parts = line.split(b" ")
    if len(parts) != 3:
        raise HttpError(HTTPStatus.BAD_REQUEST, "request line is not METHOD TARGET VERSION")
    method, target, version = parts
    if not _TOKEN.fullmatch(method):
        raise HttpError(HTTPStatus.BAD_REQUEST, "method is not a token")
    if not _VERSION.fullmatch(version):
        if _ANY_VERSION.fullmatch(version):
            raise HttpError(HTTPStatus.HTTP_VERSION_NOT_SUPPORTED, "HTTP/1.0 or HTTP/1.1 only")
        raise HttpError(HTTPStatus.BAD_REQUEST, "not an HTTP/1.x request line")
    if not _ORIGIN_FORM.fullmatch(target):
        raise HttpError(HTTPStatus.BAD_REQUEST, "request target is not a path")
    return method.decode("ascii"), target.decode("ascii"), version.decode("ascii")


def _header(line: bytes) -> tuple[str, str]:
    name, colon, value = line.partition(b":")
    if not colon or not _TOKEN.fullmatch(name):  # also refuses obs-fold (leading space)
        raise HttpError(HTTPStatus.BAD_REQUEST, "malformed header line")
    value = value.strip(b" \t")
    if not _FIELD_VALUE.fullmatch(value):
        raise HttpError(HTTPStatus.BAD_REQUEST, "header value with control or non-ASCII bytes")
    return name.decode("ascii").lower(), value.decode("ascii")


def render_response(
    status: HTTPStatus,
    body: bytes,
    content_type: str,
    *,
    head_only: bool = False,
    csp: str = DEFAULT_CSP,
    extra_headers: tuple[tuple[str, str], ...] = (),
) -> bytes:
    """A whole HTTP/1.1 response; the connection closes after it."""
    headers = [
        ("Content-Type", content_type),
        ("Content-Length", str(len(body))),
        ("Connection", "close"),
        ("Content-Security-Policy", csp),
        *SECURITY_HEADERS,
        *extra_headers,
    ]
    head = f"HTTP/1.1 {int(status)} {status.phrase}\r\n" + "".join(
        f"{name}: {value}\r\n" for name, value in headers
    )
    return head.encode("ascii") + b"\r\n" + (b"" if head_only else body)


def error_response(error: HttpError, *, head_only: bool = False) -> bytes:
    """The plain-text answer to a refused request."""
    extra = (("Allow", ", ".join(ALLOWED_METHODS)),) if error.status == 405 else ()
    body = f"{int(error.status)} {error.status.phrase}: {error.reason}\n".encode()
    return render_response(
        error.status,
        body,
        "text/plain; charset=utf-8",
        head_only=head_only,
        extra_headers=extra,
    )
