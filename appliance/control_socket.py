"""The local control socket: `dbw status` and the bench commands talk to the daemon here.

A Unix stream socket owned by the service user, mode 0660: whoever may move the vehicle
needs the socket's permissions, and there is no network listener at all. The protocol is
newline-delimited JSON, one reply per request, many requests per connection::

    {"op": "status"}                    -> {"ok": true, "status": {...}}
    {"op": "command", "name": "engage"} -> {"ok": true, "accepted": false, "message": "..."}
    anything wrong                      -> {"ok": false, "error": "what is wrong"}

The server trusts nothing a client does: lines are bounded, a bad request gets an error
reply and the connection stays usable, clients are few and may not idle, and a client
that vanishes mid-request is simply forgotten. A connection that pressed ``hold`` and
ends without ``release`` releases on its way out, so a killed `dbw hold` (or a dropped
ssh session) cannot leave the hold-to-move button pressed.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import socket
import stat
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Protocol

from appliance.control_protocol import (
    MAX_LINE_BYTES,
    ManeuverRequest,
    RequestError,
    RouteRequest,
    SamplesRequest,
    StatusRequest,
    decode_request,
    encode_message,
    error_reply,
)
from appliance.logs import get_logger
from appliance.supervisor import PermanentServiceError, ServiceContext

log = get_logger("control_socket")

MAX_PATH_BYTES: Final = 107  # sun_path is 108 bytes including the terminating NUL
BEAT_PERIOD_S: Final = 0.1
STALE_PROBE_TIMEOUT_S: Final = 0.5
CLOSE_CLIENTS_TIMEOUT_S: Final = 0.3
BAD_REQUEST_KEPT_BYTES: Final = 256  # of a refused line, for the recording
_PERMANENT_BIND_ERRNOS: Final = frozenset(
    {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.ENAMETOOLONG}
)


class ControlApi(Protocol):
    """What the daemon offers the control socket."""

    def status(self) -> dict[str, Any]:
        """A JSON-serialisable snapshot of the daemon's state."""
        ...

    def request(self, name: str) -> tuple[bool, str]:
        """Ask for one of :data:`COMMAND_NAMES`; (accepted, message). Must not block."""
        ...

    def select_route(self, name: str) -> tuple[bool, str]:
        """Select the route the autopilot follows; (accepted, message). Must not block."""
        ...

    def maneuver(self, action: str, step: str) -> tuple[bool, str]:
        """Start or stop a calibration maneuver's tap; (accepted, message)."""
        ...

    def samples(self, since: int, limit: int) -> dict[str, Any]:
        """The tapped samples from ``since`` on (see ``appliance.core.maneuver_tap``)."""
        ...


@dataclass(frozen=True)
class PeerCredentials:
    """Who is on the other end (SO_PEERCRED); None where the kernel does not say."""

    pid: int | None
    uid: int | None
    gid: int | None

    def as_log_fields(self) -> dict[str, int | None]:
        return {"peer_pid": self.pid, "peer_uid": self.uid, "peer_gid": self.gid}


_UNKNOWN_PEER: Final = PeerCredentials(None, None, None)


def peer_credentials(writer: asyncio.StreamWriter) -> PeerCredentials:
    sock = writer.get_extra_info("socket")
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
        pid, uid, gid = struct.unpack("3i", raw)
    except (OSError, AttributeError, struct.error):
        return _UNKNOWN_PEER
    return PeerCredentials(pid, uid, gid)


@dataclass
class _Session:
    peer: PeerCredentials
    holding: bool = False
    # This client armed the pedal sweep (`dbw calibrate pedals`): a sweep must not outlive
    # the command that watches it, or the next engagement would run it again.
    sweeping: bool = False


class ControlServer:
    """The daemon's side of the control socket, run as a supervised service."""

    def __init__(
        self,
        path: str | Path,
        api: ControlApi,
        *,
        mode: int = 0o660,
        max_clients: int = 8,
        idle_timeout_s: float = 30.0,
    ) -> None:
        if max_clients < 1:
            raise ValueError(f"max_clients must be at least 1 (got {max_clients})")
        if not idle_timeout_s > 0:
            raise ValueError(f"idle_timeout_s must be positive (got {idle_timeout_s})")
        self.path = Path(path)
        self.api = api
        self.mode = mode
        self.max_clients = max_clients
        self.idle_timeout_s = idle_timeout_s
        self._clients: dict[asyncio.Task[Any], asyncio.StreamWriter] = {}

    @property
    def client_count(self) -> int:
        return len(self._clients)

    async def run(self, ctx: ServiceContext) -> None:
        """Bind, serve until cancelled, and remove the socket file on the way out."""
        ctx.beat()
        sock, identity = await self._bind()
        try:
            server = await asyncio.start_unix_server(
                self._serve_client, sock=sock, limit=MAX_LINE_BYTES
            )
        except BaseException:
            sock.close()
            self._remove_socket_file(identity)
            raise
        log.info("control_socket_listening", path=str(self.path), mode=oct(self.mode))
        try:
            while True:
                ctx.beat()
                self._check_still_ours(identity)
                await asyncio.sleep(BEAT_PERIOD_S)
        finally:
            server.close()
            self._remove_socket_file(identity)
            await self._close_clients()
            log.info("control_socket_closed", path=str(self.path))

    # ---- binding -----------------------------------------------------------------
    async def _bind(self) -> tuple[socket.socket, tuple[int, int]]:
        path = self.path
        if len(os.fsencode(path)) > MAX_PATH_BYTES:
            raise PermanentServiceError(
                f"control socket path {str(path)!r} is {len(os.fsencode(path))} bytes; Unix "
                f"socket paths are limited to {MAX_PATH_BYTES}: set a shorter "
                "paths.control_socket"
            )
        self._make_parent_directory()
        await self._remove_stale_socket()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        identity: tuple[int, int] | None = None
        try:
            # Bind under an owner-only umask, then open up to the mode: the socket is never
            # reachable by more than its owner before the chmod. (The umask is process-wide;
            # anything another thread creates meanwhile is only more private.)
            previous_umask = os.umask(0o077)
            try:
                sock.bind(os.fspath(path))
            finally:
                os.umask(previous_umask)
            identity = _identity(os.lstat(path))
            os.chmod(path, self.mode)
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            if identity is not None:
                self._remove_socket_file(identity)
            if exc.errno == errno.EADDRINUSE:
                raise  # someone bound it meanwhile: a restart probes again
            if exc.errno in _PERMANENT_BIND_ERRNOS:
                raise PermanentServiceError(
                    f"cannot create the control socket {str(path)!r}: {exc.strerror}"
                ) from exc
            raise
        return sock, identity

    def _make_parent_directory(self) -> None:
        parent = self.path.parent
        if parent.is_dir():
            return
        try:
            os.makedirs(parent, mode=0o750, exist_ok=True)
            os.chmod(parent, 0o750)
        except OSError as exc:
            raise PermanentServiceError(
                f"cannot create the directory {str(parent)!r} for the control socket: "
                f"{exc.strerror or exc}"
            ) from exc
        log.info("control_socket_directory_created", path=str(parent), mode="0o750")

    async def _remove_stale_socket(self) -> None:
        path = self.path
        try:
            info = os.lstat(path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(info.st_mode):
            raise PermanentServiceError(
                f"{str(path)!r} exists and is not a socket: refusing to replace it; move it "
                "away or set another paths.control_socket"
            )
        try:
            async with asyncio.timeout(STALE_PROBE_TIMEOUT_S):
                _, writer = await asyncio.open_unix_connection(os.fspath(path))
        except ConnectionRefusedError:
            os.unlink(path)
            log.warning("control_socket_stale_removed", path=str(path))
            return
        except FileNotFoundError:
            return
        except TimeoutError:
            raise PermanentServiceError(
                f"{str(path)!r} is a socket another process listens on but does not accept "
                "connections: another daemon may be running (`systemctl status dbw`)"
            ) from None
        except OSError as exc:
            raise PermanentServiceError(
                f"cannot check whether {str(path)!r} is in use: {exc.strerror or exc}"
            ) from exc
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()
        raise PermanentServiceError(
            f"another daemon is already serving the control socket {str(path)!r}: stop it "
            "first (`systemctl stop dbw`) or set another paths.control_socket"
        )

    def _check_still_ours(self, identity: tuple[int, int]) -> None:
        try:
            current = _identity(os.lstat(self.path))
        except FileNotFoundError:
            current = None
        if current != identity:
            raise RuntimeError(f"the control socket {str(self.path)!r} was removed or replaced")

    def _remove_socket_file(self, identity: tuple[int, int]) -> None:
        """Unlink the socket file if it is still the one we bound (never someone else's)."""
        with contextlib.suppress(OSError):
            if _identity(os.lstat(self.path)) == identity:
                os.unlink(self.path)

    async def _close_clients(self) -> None:
        """Hang up on every client and wait until their handlers have finished.

        Aborting the transport lets a handler see end-of-stream and return on its own;
        cancelling it instead would make Python 3.11's stream protocol log the
        cancellation as an unhandled error.
        """
        tasks = list(self._clients)
        for writer in self._clients.values():
            writer.transport.abort()
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=CLOSE_CLIENTS_TIMEOUT_S)
            for task in pending:
                task.cancel()

    # ---- clients -----------------------------------------------------------------
    async def _serve_client(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        peer = peer_credentials(writer)
        if len(self._clients) >= self.max_clients:
            log.warning(
                "control_client_refused", clients=len(self._clients), **peer.as_log_fields()
            )
            writer.write(
                encode_message(
                    error_reply(
                        f"too many clients: at most {self.max_clients} at a time; try again later"
                    )
                )
            )
            writer.close()
            return
        task = asyncio.current_task()
        assert task is not None
        self._clients[task] = writer
        session = _Session(peer)
        log.debug("control_client_connected", **peer.as_log_fields())
        try:
            await self._converse(reader, writer, session)
        except OSError as exc:  # the client went away; nothing of ours depends on it
            log.debug("control_client_lost", error=repr(exc))
        except Exception as exc:  # a bug here must cost one connection, never the server
            log.error("control_client_failed", error=repr(exc), exc_info=exc)
        finally:
            del self._clients[task]
            if session.holding:
                self._command("release", session, cause="client disconnected while holding")
            if session.sweeping:
                log.warning("control_client_left_sweep_armed", **peer.as_log_fields())
                self._maneuver(ManeuverRequest("stop", "pedals"), session)
            writer.close()
            log.debug("control_client_disconnected", **peer.as_log_fields())

    async def _converse(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, session: _Session
    ) -> None:
        while True:
            try:
                async with asyncio.timeout(self.idle_timeout_s):
                    line = await reader.readuntil(b"\n")
            except TimeoutError:
                log.info("control_client_idle", idle_s=self.idle_timeout_s)
                writer.write(
                    encode_message(
                        error_reply(f"no request for {self.idle_timeout_s:g} s: closing")
                    )
                )
                return
            except asyncio.IncompleteReadError:
                return  # end of stream, possibly mid-line: the client left
            except asyncio.LimitOverrunError:
                log.info("control_request_too_long", **session.peer.as_log_fields())
                await self._send(
                    writer,
                    error_reply(
                        f"request line longer than {MAX_LINE_BYTES} bytes: closing the "
                        "connection (the rest of that line cannot be framed)"
                    ),
                )
                return
            if not await self._send(writer, self._answer(line, session)):
                return

    async def _send(self, writer: asyncio.StreamWriter, reply: Mapping[str, Any]) -> bool:
        """Write one reply; False if the client does not take it in time."""
        writer.write(encode_message(reply))
        try:
            async with asyncio.timeout(self.idle_timeout_s):
                await writer.drain()
        except TimeoutError:
            log.info("control_client_not_reading", timeout_s=self.idle_timeout_s)
            return False
        return True

    def _answer(self, line: bytes, session: _Session) -> dict[str, Any]:
        try:
            request = decode_request(line)
        except RequestError as exc:
            log.info("control_bad_request", error=str(exc), **session.peer.as_log_fields())
            told = getattr(self.api, "bad_request", None)
            if told is not None:  # the recorder keeps every input, the refused ones too
                try:
                    told(line[:BAD_REQUEST_KEPT_BYTES].decode("utf-8", "replace"), str(exc))
                except Exception as err:  # a recorder's trouble is no reason to drop a client
                    log.error("control_bad_request_not_told", error=repr(err), exc_info=err)
            return error_reply(str(exc))
        if isinstance(request, StatusRequest):
            try:
                return {"ok": True, "status": self.api.status()}
            except Exception as exc:
                log.error("control_status_failed", error=repr(exc), exc_info=exc)
                return error_reply(f"the daemon could not produce its status: {exc!r}")
        if isinstance(request, RouteRequest):
            return self._select_route(request.select, session)
        if isinstance(request, ManeuverRequest):
            return self._maneuver(request, session)
        if isinstance(request, SamplesRequest):
            try:
                return {"ok": True, **self.api.samples(request.since, request.limit)}
            except Exception as exc:
                log.error("control_samples_failed", error=repr(exc), exc_info=exc)
                return error_reply(f"the daemon could not give its samples: {exc!r}")
        return self._command(request.name, session)

    def _maneuver(self, request: ManeuverRequest, session: _Session) -> dict[str, Any]:
        reply = self._verdict(
            "maneuver",
            f"{request.action} {request.step!r}",
            lambda: self.api.maneuver(request.action, request.step),
            session,
            action=request.action,
            step=request.step,
        )
        if request.step.partition("@")[0] == "pedals" and reply.get("accepted"):
            session.sweeping = request.action == "start"
        return reply

    def _select_route(self, name: str, session: _Session) -> dict[str, Any]:
        return self._verdict(
            "route_select",
            f"select route {name!r}",
            lambda: self.api.select_route(name),
            session,
            route=name,
        )

    def _verdict(
        self,
        event: str,
        doing: str,
        call: Callable[[], tuple[bool, str]],
        session: _Session,
        **fields: Any,
    ) -> dict[str, Any]:
        """A request the daemon accepts or refuses with a reason: logged with who asked, and
        answered; an exception in the daemon is an error reply, never a dropped session."""
        try:
            accepted, message = call()
        except Exception as exc:
            log.error(event, error=repr(exc), exc_info=exc, **fields)
            return error_reply(f"the daemon failed to {doing}: {exc!r}")
        log.info(
            event,
            **fields,
            verdict="accepted" if accepted else "refused",
            message=message,
            **session.peer.as_log_fields(),
        )
        return {"ok": True, "accepted": bool(accepted), "message": str(message)}

    def _command(self, name: str, session: _Session, cause: str = "client") -> dict[str, Any]:
        try:
            accepted, message = self.api.request(name)
        except Exception as exc:
            log.error(
                "control_command",
                command=name,
                verdict="error",
                error=repr(exc),
                cause=cause,
                exc_info=exc,
                **session.peer.as_log_fields(),
            )
            return error_reply(f"the daemon failed to handle {name!r}: {exc!r}")
        accepted = bool(accepted)
        message = str(message)
        log.info(
            "control_command",
            command=name,
            verdict="accepted" if accepted else "refused",
            message=message,
            cause=cause,
            **session.peer.as_log_fields(),
        )
        if name == "hold" and accepted:
            session.holding = True
        elif name == "release":
            session.holding = False
        return {"ok": True, "accepted": accepted, "message": message}


def _identity(info: os.stat_result) -> tuple[int, int]:
    return info.st_dev, info.st_ino
