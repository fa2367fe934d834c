"""One TCP session with an LMS111: connect, ask and wait for the answer, read the stream.

Shared by the client, `probe` and the recorder, so the three agree on what a reply is and
what counts as a failure. Two kinds of failure, because they need opposite reactions:

* `Lms111LinkError` — the link or the device's timing failed (refused, reset, closed, no
  answer in time, a stall, "server busy"). Transient: reconnect with backoff. A scanner that
  is still booting looks exactly like this for up to ~30 s (clearpath LMS1xx #11, sick_scan
  #4, sick_scan_xd #383), so it must never be fatal.
* `Lms111ConfigError` — the scanner understood the request and refused it (``sFA`` with a
  SOPAS error, ``sAN SetAccessMode 0``, a set-scan-config status other than 0). Retrying
  gets the same answer forever (sick_scan_xd #227: "I kill the process because it keeps
  restarting"), so it goes up to the supervisor with the command and the reason.

Telegrams that arrive while waiting for an answer are not lost: scans are queued for the
stream, unsolicited events (``sSN LIDoutputstate`` ...) are skipped. The device answers one
request at a time, so an ``sFA`` (which carries no name) belongs to the outstanding one.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Final

from drivers.lms111.cola import Command, CommandType, ErrorReply, Event, Reply, ScanTelegram
from drivers.lms111.connection import Lms111Connection
from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import NEED_DATA, Dialect
from drivers.lms111.scan import Scan

READ_CHUNK_BYTES: Final = 65536
SERVER_BUSY: Final = 0x0D  # Sopas_Error_METHODIN_SERVER_BUSY: transient, not a refusal

_ANSWER_KIND: Final = {
    CommandType.SRN: CommandType.SRA,
    CommandType.SWN: CommandType.SWA,
    CommandType.SMN: CommandType.SAN,
    CommandType.SEN: CommandType.SEA,
}

Clock = Callable[[], float]
BytesHook = Callable[[bytes, float], None]
# Awaited before received bytes are framed and decoded: the runtime's way to keep a scan's
# decoding out of the moments before a control deadline (appliance.timing.ControlSlot).
Gate = Callable[[], Awaitable[None]]
ErrorHook = Callable[[ProtocolError], None]


class Lms111Error(Exception):
    """Base of the driver's own errors."""


class Lms111LinkError(Lms111Error):
    """The link or the device's timing failed; reconnecting may help."""


class Lms111ConfigError(Lms111Error):
    """The scanner refused a request during set-up; reconnecting will not help.

    ``command`` is the request's name (``mLMPsetscancfg``), ``code`` the SOPAS error or
    status code (None when the answer carries none), ``meaning`` what it says in words.
    """

    def __init__(self, command: str, code: int | None, meaning: str, scanner: str = "") -> None:
        self.command = command
        self.code = code
        self.meaning = meaning
        self.scanner = scanner
        code_text = "" if code is None else f" (code {code:#x})"
        where = f"LMS111 {scanner!r}" if scanner else "LMS111"
        super().__init__(f"{where} refused {command}: {meaning}{code_text}")


class Lms111LoginError(Lms111ConfigError):
    """``SetAccessMode`` was refused: wrong password or user level."""


class SopasRefused(Lms111Error):
    """``sFA`` in answer to a request (the caller decides whether that is fatal)."""

    def __init__(self, command: Command, error: ErrorReply) -> None:
        self.command = command
        self.error = error
        super().__init__(f"{command.kind.value} {command.name}: sFA {error.code:X} {error.meaning}")


def refusal_to_config_error(exc: SopasRefused, scanner: str = "") -> Lms111Error:
    """ "Server busy" is transient (a link problem); every other ``sFA`` is a refusal."""
    if exc.error.code == SERVER_BUSY:
        return Lms111LinkError(str(exc))
    return Lms111ConfigError(
        exc.command.name, exc.error.code, f"{exc.error.constant}: {exc.error.meaning}", scanner
    )


class Lms111Session:
    """A connected stream plus the sans-I/O core; ``request`` and ``read_events``.

    ``on_bytes(data, receive_time_s)`` sees every chunk as read (the recorder writes them
    to disk); ``on_protocol_error`` sees each dropped telegram (the client counts and logs).
    """

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        dialect: Dialect = Dialect.COLA_A,
        *,
        clock: Clock = time.monotonic,
        request_timeout_s: float = 2.0,
        on_bytes: BytesHook | None = None,
        on_protocol_error: ErrorHook | None = None,
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.connection = Lms111Connection(dialect)
        self.clock = clock
        self.request_timeout_s = request_timeout_s
        self.on_bytes = on_bytes
        self.on_protocol_error = on_protocol_error
        self.queued_scans: deque[Scan] = deque(maxlen=64)
        self.bytes_received = 0
        self.before_decode: Gate | None = None

    @classmethod
    async def connect(
        cls,
        host: str,
        port: int,
        dialect: Dialect = Dialect.COLA_A,
        *,
        connect_timeout_s: float = 2.0,
        clock: Clock = time.monotonic,
        request_timeout_s: float = 2.0,
        on_bytes: BytesHook | None = None,
        on_protocol_error: ErrorHook | None = None,
    ) -> Lms111Session:
        """Open the TCP connection; every failure is an `Lms111LinkError`."""
        try:
            async with asyncio.timeout(connect_timeout_s):
                reader, writer = await asyncio.open_connection(host, port)
        except TimeoutError as exc:
            raise Lms111LinkError(f"connect to {host}:{port} timed out") from exc
        except OSError as exc:
            reason = exc.strerror or str(exc)
            raise Lms111LinkError(f"connect to {host}:{port} failed: {reason}") from exc
        sock = writer.get_extra_info("socket")
        if sock is not None:  # small requests must not wait for Nagle
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return cls(
            reader,
            writer,
            dialect,
            clock=clock,
            request_timeout_s=request_timeout_s,
            on_bytes=on_bytes,
            on_protocol_error=on_protocol_error,
        )

    async def close(self) -> None:
        """Close without waiting on a peer that may be gone (abort after a short grace)."""
        self.writer.close()
        try:
            async with asyncio.timeout(0.2):
                await self.writer.wait_closed()
        except (TimeoutError, OSError):
            self.writer.transport.abort()

    async def send(self, command: Command) -> None:
        try:
            self.writer.write(self.connection.send(command))
            async with asyncio.timeout(self.request_timeout_s):
                await self.writer.drain()
        except TimeoutError as exc:
            raise Lms111LinkError(f"send {command.name}: the scanner is not reading") from exc
        except OSError as exc:
            raise Lms111LinkError(f"send {command.name} failed: {exc}") from exc

    async def read_events(self, timeout_s: float) -> list[Event]:
        """Read once (waiting at most ``timeout_s``), feed the core, return what it framed.

        Raises `TimeoutError` when nothing arrived in time, `Lms111LinkError` when the
        connection closed or failed.
        """
        try:
            async with asyncio.timeout(max(timeout_s, 0.0)):
                data = await self.reader.read(READ_CHUNK_BYTES)
        except TimeoutError:  # a subclass of OSError: let the caller decide what it means
            raise
        except OSError as exc:
            raise Lms111LinkError(f"read failed: {exc}") from exc
        if not data:
            raise Lms111LinkError("the scanner closed the connection")
        now_s = self.clock()
        self.bytes_received += len(data)
        if self.on_bytes is not None:
            self.on_bytes(data, now_s)
        if self.before_decode is not None:
            await self.before_decode()  # the scans keep their receive time, now_s
        self.connection.receive_data(data)
        return self.drain(now_s)

    def drain(self, now_s: float) -> list[Event]:
        events: list[Event] = []
        while True:
            try:
                event = self.connection.next_event(host_receive_time_s=now_s)
            except ProtocolError as exc:  # already dropped by the core: count and go on
                if self.on_protocol_error is not None:
                    self.on_protocol_error(exc)
                continue
            if event is NEED_DATA:
                return events
            events.append(event)

    async def request(self, command: Command, *, timeout_s: float | None = None) -> Reply:
        """Send ``command`` and return its answer (``sMA`` is skipped: the ``sAN`` follows).

        `SopasRefused` on ``sFA``; `Lms111LinkError` if no answer arrives in time.
        """
        await self.send(command)
        expected = _ANSWER_KIND[command.kind]
        deadline_s = self.clock() + (self.request_timeout_s if timeout_s is None else timeout_s)
        while True:
            try:
                events = await self.read_events(deadline_s - self.clock())
            except TimeoutError as exc:
                raise Lms111LinkError(
                    f"no answer to {command.kind.value} {command.name} "
                    f"within {self.request_timeout_s:.1f} s"
                ) from exc
            answer: Reply | None = None
            for event in events:
                if isinstance(event, ScanTelegram):
                    self.queued_scans.append(event.scan)
                elif isinstance(event, ErrorReply):
                    raise SopasRefused(command, event)
                elif event.kind is expected and event.name == command.name and answer is None:
                    answer = event
            if answer is not None:
                return answer
