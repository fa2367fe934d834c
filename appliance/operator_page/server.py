"""The operator page: a read-only view of the daemon, over HTTP on 127.0.0.1.

A thin asyncio shell around :mod:`appliance.operator_page.http`: read a connection's
bytes into the request reader under one deadline, answer from a fixed table of three
paths, close. Nothing a client sends can reach the daemon's state (there is no request
that changes anything), the file system (the page is read once, at construction) or the
event loop for long (every connection has a deadline, and there are few of them).

Loopback only, unless the vehicle file says otherwise (``allow_non_loopback``); a server
on loopback also refuses requests whose Host is not a loopback name, so a web page the
operator happens to open cannot read the vehicle's state through DNS rebinding.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import errno
import hashlib
import ipaddress
import json
import math
import re
from collections.abc import Callable
from http import HTTPStatus
from importlib import resources
from typing import Any, Final, Protocol

from appliance.logs import get_logger
from appliance.operator_page.http import (
    NEED_DATA,
    ConnectionClosed,
    HttpError,
    Request,
    RequestReader,
    error_response,
    render_response,
)
from appliance.supervisor import PermanentServiceError

log = get_logger("operator_page")

BEAT_PERIOD_S: Final = 1.0
READ_CHUNK_BYTES: Final = 4096
CLOSE_CLIENTS_TIMEOUT_S: Final = 0.3
# A connection over the limit gets this long to send its request before its 503, and at
# most this many times the limit wait so; beyond that they are dropped unanswered.
BUSY_READ_S: Final = 1.0
BUSY_BACKLOG_FACTOR: Final = 4
JSON_TYPE: Final = "application/json"
_PERMANENT_BIND_ERRNOS: Final = frozenset({errno.EACCES, errno.EPERM, errno.EADDRNOTAVAIL})
_INLINE: Final = re.compile(rb"<(script|style)>(.*?)</\1>", re.DOTALL)


class Beats(Protocol):
    """What the server needs of its supervisor: a way to prove it is alive."""

    def beat(self) -> None: ...


StatusSource = Callable[[], dict[str, Any]]


def is_loopback(host: str) -> bool:
    """``localhost`` or a literal loopback address (127.0.0.0/8, ::1)."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def host_header_name(value: str) -> str:
    """The name part of a Host header: ``[::1]:8080`` -> ``::1``, ``a:80`` -> ``a``."""
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else value
    return value.rpartition(":")[0] if ":" in value else value


def load_page() -> bytes:
    """The page as shipped (package data), read once."""
    return resources.files("appliance.operator_page").joinpath("static/index.html").read_bytes()


def page_csp(page: bytes) -> str:
    """``default-src 'self'`` plus the hashes of the page's own inline script and style,
    so exactly those run and nothing injected would."""
    sources: dict[str, list[str]] = {"script": [], "style": []}
    for kind, content in _INLINE.findall(page):
        digest = base64.b64encode(hashlib.sha256(content).digest()).decode("ascii")
        sources[kind.decode("ascii")].append(f"'sha256-{digest}'")
    if not sources["script"]:
        raise ValueError("the operator page has no inline <script> to allow")
    policy = ["default-src 'self'", "script-src " + " ".join(sources["script"])]
    if sources["style"]:
        policy.append("style-src " + " ".join(sources["style"]))
    return "; ".join([*policy, "img-src 'self'", "frame-ancestors 'none'", "form-action 'none'"])


def json_bytes(value: object) -> bytes:
    """JSON a browser can parse: non-finite floats become null, odd objects strings."""
    try:
        text = json.dumps(value, allow_nan=False, default=str, separators=(",", ":"))
    except ValueError:
        text = json.dumps(_finite(value), allow_nan=False, default=str, separators=(",", ":"))
    return text.encode("utf-8")


def _finite(value: object) -> object:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value


async def read_request(
    reader: asyncio.StreamReader, parser: RequestReader
) -> Request | ConnectionClosed:
    """Feed the parser from the stream until it has a request; raises HttpError."""
    while True:
        event = parser.next_event()
        if event is not NEED_DATA:
            assert isinstance(event, Request | ConnectionClosed)
            return event
        parser.receive_data(await reader.read(READ_CHUNK_BYTES))


class OperatorPage:
    """The page and its two JSON documents, served by the daemon as a supervised service."""

    max_body_bytes = 0  # GET and HEAD only: a request with a body is refused

    def __init__(
        self,
        status: StatusSource,
        scans: StatusSource | None,
        host: str = "127.0.0.1",
        port: int = 8080,
        *,
        allow_non_loopback: bool = False,
        max_connections: int = 8,
        request_timeout_s: float = 5.0,
        page: bytes | None = None,
    ) -> None:
        loopback = is_loopback(host)
        if not loopback and not allow_non_loopback:
            raise ValueError(
                f"operator page host {host!r} is not a loopback address: the page listens on "
                "127.0.0.1 unless the vehicle file sets operator_page.allow_non_loopback = true"
            )
        if not 0 <= port <= 65535:
            raise ValueError(f"operator page port must be 0..65535 (got {port})")
        if max_connections < 1:
            raise ValueError(f"max_connections must be at least 1 (got {max_connections})")
        if not request_timeout_s > 0:
            raise ValueError(f"request_timeout_s must be positive (got {request_timeout_s})")
        self.status = status
        self.scans = scans
        self.host = host
        self.port = port
        self.check_host_header = loopback
        self.max_connections = max_connections
        self.request_timeout_s = request_timeout_s
        self.page = load_page() if page is None else page
        self.csp = page_csp(self.page)
        self.refused = 0  # connections turned away with 503
        self._refusing = 0
        self._bound_port: int | None = None
        self._clients: dict[asyncio.Task[Any], asyncio.StreamWriter] = {}
        self._last_failure = ""

    @property
    def bound_port(self) -> int | None:
        """The port listened on (the one picked when ``port`` is 0); None when not listening."""
        return self._bound_port

    @property
    def connection_count(self) -> int:
        return len(self._clients)

    async def run(self, ctx: Beats) -> None:
        """Listen, serve until cancelled, hang up on every client on the way out."""
        try:
            server = await asyncio.start_server(
                self._serve_client, self.host, self.port, reuse_address=True
            )
        except OSError as exc:
            where = f"{self.host}:{self.port}"
            if exc.errno in _PERMANENT_BIND_ERRNOS:
                raise PermanentServiceError(
                    f"the operator page cannot listen on {where}: {exc.strerror or exc}; set "
                    "another operator_page.host or port"
                ) from exc
            raise  # in use (another daemon, a lingering socket): a restart tries again
        try:
            self._bound_port = int(server.sockets[0].getsockname()[1])
            log.info("operator_page_listening", host=self.host, port=self._bound_port)
            while True:
                ctx.beat()
                await asyncio.sleep(BEAT_PERIOD_S)
        finally:
            self._bound_port = None
            server.close()
            await self._close_clients()
            log.info("operator_page_closed", host=self.host)

    async def _close_clients(self) -> None:
        """Abort every connection and let its handler see the end (see control_socket)."""
        tasks = list(self._clients)
        for writer in self._clients.values():
            writer.transport.abort()
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=CLOSE_CLIENTS_TIMEOUT_S)
            for task in pending:
                task.cancel()

    # ---- one connection ----------------------------------------------------------
    async def _serve_client(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        if len(self._clients) >= self.max_connections:
            await self._refuse_busy(reader, writer)
            return
        task = asyncio.current_task()
        assert task is not None
        self._clients[task] = writer
        # drain() then waits until every byte is with the kernel, so the close below never
        # leaves a response queued in the process for a client that stopped reading.
        writer.transport.set_write_buffer_limits(high=0)
        answered = False
        try:
            async with asyncio.timeout(self.request_timeout_s):
                response = await self._read_and_answer(reader)
                if response:
                    writer.write(response)
                    await writer.drain()
            answered = True
        except TimeoutError:
            log.debug("operator_page_client_timeout", timeout_s=self.request_timeout_s)
        except OSError as exc:  # the client went away
            log.debug("operator_page_client_lost", error=repr(exc))
        except Exception as exc:  # a bug here costs one connection, never the server
            log.error("operator_page_client_failed", error=repr(exc), exc_info=exc)
        finally:
            del self._clients[task]
            if answered:
                writer.close()  # the response is in the kernel's buffer: a normal close
            else:
                writer.transport.abort()  # slow, gone or hostile: drop whatever is queued

    async def _refuse_busy(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        """503, after taking the request off the wire (closing on unread bytes would reset
        the connection before the client read the answer); briefly, and only for a few."""
        self.refused += 1
        if self.refused == 1 or self.refused % 100 == 0:
            log.warning("operator_page_busy", connections=len(self._clients), refused=self.refused)
        if self._refusing >= self.max_connections * BUSY_BACKLOG_FACTOR:
            writer.transport.abort()  # a flood: no answer at all
            return
        self._refusing += 1
        try:
            # Whatever it is (a POST, garbage): the answer is 503 all the same.
            with contextlib.suppress(TimeoutError, OSError, HttpError):
                async with asyncio.timeout(BUSY_READ_S):
                    await read_request(reader, RequestReader())
            busy = HttpError(HTTPStatus.SERVICE_UNAVAILABLE, "too many connections, try again")
            writer.write(error_response(busy))  # small: fits the socket buffer, never waits
            writer.close()
        finally:
            self._refusing -= 1

    async def _read_and_answer(self, reader: asyncio.StreamReader) -> bytes:
        try:
            event = await read_request(reader, RequestReader(max_body_bytes=self.max_body_bytes))
        except HttpError as error:
            return error_response(error)
        if isinstance(event, ConnectionClosed):
            return b""
        return self.respond(event)

    def respond(self, request: Request) -> bytes:
        """The answer to one well-formed request (pure but for the two sources)."""
        head_only = request.method == "HEAD"
        try:
            self._check_host(request)
            content_type, body = self._resource(request.path)
        except HttpError as error:
            return error_response(error, head_only=head_only)
        return render_response(HTTPStatus.OK, body, content_type, head_only=head_only, csp=self.csp)

    def _check_host(self, request: Request) -> None:
        host = request.header("host")
        if self.check_host_header and host is not None and not is_loopback(host_header_name(host)):
            raise HttpError(HTTPStatus.MISDIRECTED_REQUEST, "Host is not a loopback name")

    def _resource(self, path: str) -> tuple[str, bytes]:
        if path == "/":
            return "text/html; charset=utf-8", self.page
        if path == "/status.json":
            return JSON_TYPE, self._document("status", self.status)
        if path == "/scans.json" and self.scans is not None:
            return JSON_TYPE, self._document("scans", self.scans)
        raise HttpError(HTTPStatus.NOT_FOUND, "no such page")

    def _document(self, what: str, source: StatusSource) -> bytes:
        try:
            body = json_bytes(source())
        except Exception as exc:
            failure = f"{what}: {exc!r}"
            if failure != self._last_failure:  # once per kind of failure, not per poll
                log.error("operator_page_source_failed", source=what, error=repr(exc))
            self._last_failure = failure
            raise HttpError(
                HTTPStatus.INTERNAL_SERVER_ERROR, f"the daemon could not produce its {what}"
            ) from exc
        self._last_failure = ""
        return body
