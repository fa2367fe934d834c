"""The other end of the control socket: how `dbw status`, `dbw engage` and tests ask.

Every failure to talk to the daemon (no daemon, no permission, a hung or overloaded one,
a reply too long or not JSON) becomes one :class:`ControlSocketError` with a sentence a
person can act on; the protocol itself is :mod:`appliance.control_protocol`, the server
:mod:`appliance.control_socket`.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

from appliance.control_protocol import ControlSocketError, decode_reply, encode_message

MAX_REPLY_BYTES: Final = 1024 * 1024  # a status document with a long fault history


class ControlClient:
    """One connection to the control socket, for one or many requests.

    ``async with ControlClient(path) as client: reply = await client.call({...})``.
    Every failure to talk to the daemon raises :class:`ControlSocketError`.
    """

    def __init__(self, path: str | Path, timeout_s: float = 2.0) -> None:
        self.path = str(path)
        self.timeout_s = timeout_s
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._unanswered = 0

    async def __aenter__(self) -> ControlClient:
        await self.connect()
        return self

    async def __aexit__(self, *_: object) -> None:
        await self.close()

    async def connect(self) -> None:
        try:
            async with asyncio.timeout(self.timeout_s):
                self._unanswered = 0
                self._reader, self._writer = await asyncio.open_unix_connection(
                    self.path, limit=MAX_REPLY_BYTES
                )
        except TimeoutError:
            raise ControlSocketError(
                f"{self.path}: the daemon did not accept the connection within "
                f"{self.timeout_s:g} s (overloaded or hung?): `systemctl status dbw`"
            ) from None
        except OSError as exc:
            raise ControlSocketError(_connect_error(self.path, exc)) from None

    async def call(self, request: Mapping[str, Any]) -> dict[str, Any]:
        """Send one request and return the daemon's reply (which may be an error reply)."""
        if self._reader is None or self._writer is None:
            await self.connect()
        reader, writer = self._reader, self._writer
        assert reader is not None and writer is not None
        try:
            async with asyncio.timeout(self.timeout_s):
                while self._unanswered:  # replies to requests whose caller was cancelled
                    await reader.readuntil(b"\n")
                    self._unanswered -= 1
                writer.write(encode_message(request))  # buffers the whole line at once
                self._unanswered += 1
                await writer.drain()
                line = await reader.readuntil(b"\n")
                self._unanswered -= 1
        except asyncio.CancelledError:
            # The connection is still in step: the next call skips the replies still due,
            # so a cancelled status request (Ctrl-C) does not cost the connection.
            raise
        except BaseException as exc:
            self._reader = self._writer = None
            self._unanswered = 0
            writer.transport.abort()
            raise self._exchange_error(exc) from None
        return decode_reply(line)

    def _exchange_error(self, exc: BaseException) -> BaseException:
        if isinstance(exc, TimeoutError):
            return ControlSocketError(
                f"{self.path}: no reply from the daemon within {self.timeout_s:g} s"
            )
        if isinstance(exc, asyncio.IncompleteReadError | ConnectionError):
            return ControlSocketError(
                f"{self.path}: the daemon closed the connection before replying "
                "(stopping, or restarting?): `systemctl status dbw`"
            )
        if isinstance(exc, asyncio.LimitOverrunError):
            return ControlSocketError(
                f"{self.path}: the daemon's reply is longer than {MAX_REPLY_BYTES} bytes"
            )
        if isinstance(exc, OSError):
            return ControlSocketError(f"{self.path}: {exc.strerror or exc}")
        return exc

    async def status(self) -> dict[str, Any]:
        return await self.call({"op": "status"})

    async def command(self, name: str) -> dict[str, Any]:
        return await self.call({"op": "command", "name": name})

    async def close(self) -> None:
        writer, self._reader, self._writer = self._writer, None, None
        self._unanswered = 0
        if writer is not None:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()


def _connect_error(path: str, exc: OSError) -> str:
    if isinstance(exc, FileNotFoundError):
        return f"{path}: no control socket there: is the daemon running? `systemctl status dbw`"
    if isinstance(exc, PermissionError):
        return (
            f"{path}: permission denied: you need to be in the dbw group (or root) to use "
            "the control socket"
        )
    if isinstance(exc, ConnectionRefusedError):
        return (
            f"{path}: nobody is listening (a socket left behind by a daemon that stopped): "
            "is the daemon running? `systemctl status dbw`"
        )
    return f"{path}: cannot connect to the daemon: {exc.strerror or exc}"


async def query(
    path: str | Path, request: Mapping[str, Any], timeout_s: float = 2.0
) -> dict[str, Any]:
    """Send one request on a connection of its own; raise ControlSocketError on failure."""
    async with ControlClient(path, timeout_s) as client:
        return await client.call(request)


def query_sync(
    path: str | Path, request: Mapping[str, Any], timeout_s: float = 2.0
) -> dict[str, Any]:
    """:func:`query` for code without an event loop (the CLI)."""
    return asyncio.run(query(path, request, timeout_s))
