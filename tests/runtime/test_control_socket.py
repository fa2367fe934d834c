"""The control socket for real: a ControlServer on a Unix socket, a fake daemon behind it,
and clients that behave well, badly and not at all; then the `dbw` commands against it."""

from __future__ import annotations

import asyncio
import contextlib
import io
import itertools
import json
import logging
import os
import re
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from structlog.testing import capture_logs

from appliance.cli.control import CONTROL_COMMANDS, engage, hold, speed_up, status
from appliance.control_client import ControlClient, query, query_sync
from appliance.control_protocol import (
    COMMAND_NAMES,
    MAX_LINE_BYTES,
    CommandRequest,
    ControlSocketError,
    ManeuverRequest,
    RequestError,
    RouteRequest,
    SamplesRequest,
    StatusRequest,
    decode_request,
    encode_message,
)
from appliance.control_socket import ControlServer
from appliance.logs import configure_logging
from appliance.supervisor import PermanentServiceError

STATUS_DOC: dict[str, Any] = {
    "vehicle": "sim",
    "mode": "speed_hold",
    "mode_since_s": 12.3,
    "set_speed_mps": 1.5,
    "measured_speed_mps": 1.48,
    "hold_to_move": {"required": True, "held": False},
    "last_refusal": ["critical input stale: scan.left"],
    "inputs": {"scan.left": {"age_s": float("inf"), "limit_s": 0.1, "stale": True}},
}


class FakeApi:
    """The daemon as the control socket sees it: records requests, refuses some."""

    def __init__(self, refuse: tuple[str, ...] = ()) -> None:
        self.requests: list[str] = []
        self.refuse = set(refuse)
        self.fail_status = False
        self.fail_request = False

    def status(self) -> dict[str, Any]:
        if self.fail_status:
            raise RuntimeError("status exploded")
        return dict(STATUS_DOC)

    def request(self, name: str) -> tuple[bool, str]:
        if self.fail_request:
            raise RuntimeError("request exploded")
        self.requests.append(name)
        if name in self.refuse:
            return False, f"{name} refused: not READY"
        return True, f"{name} done"

    def select_route(self, name: str) -> tuple[bool, str]:
        self.requests.append(f"route:{name}")
        if name == "missing":
            return False, "route 'missing' not selected: no such route"
        return True, f"route {name!r} selected"

    def maneuver(self, action: str, step: str) -> tuple[bool, str]:
        self.requests.append(f"maneuver:{action}:{step}")
        if step == "warp":
            return False, "unknown maneuver 'warp'"
        return True, f"{action} {step}"

    def samples(self, since: int, limit: int) -> dict[str, Any]:
        self.requests.append(f"samples:{since}:{limit}")
        first = max(since, 10)
        return {
            "step": "pot-map",
            "active": True,
            "samples": [{"seq": n} for n in range(first, first + min(limit, 3))],
            "next": first + min(limit, 3),
            "missed": first - since,
        }


@dataclass
class FakeContext:
    beats: list[float] = field(default_factory=list)

    def beat(self) -> None:
        self.beats.append(time.monotonic())


@dataclass
class Served:
    server: ControlServer
    api: FakeApi
    ctx: FakeContext
    task: asyncio.Task[None]
    path: Path


async def wait_until(predicate: Callable[[], bool], timeout_s: float = 2.0) -> None:
    async def poll() -> None:
        while not predicate():
            await asyncio.sleep(0.005)

    await asyncio.wait_for(poll(), timeout_s)


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    # Unix socket paths are limited to 108 bytes; pytest's tmp_path can be longer
    # (the same way tests/runtime/conftest.py makes the notify socket's directory).
    directory = Path(tempfile.mkdtemp(prefix="dbw-", dir="/tmp"))
    try:
        yield directory
    finally:
        for sub in directory.rglob("*"):  # a test may have locked a directory
            with contextlib.suppress(OSError):
                if sub.is_dir() and not sub.is_symlink():
                    sub.chmod(0o700)
        shutil.rmtree(directory, ignore_errors=True)


@contextlib.asynccontextmanager
async def serving(path: Path, api: FakeApi | None = None, **options: Any) -> AsyncIterator[Served]:
    api = api if api is not None else FakeApi()
    server = ControlServer(path, api, **options)
    ctx = FakeContext()
    task = asyncio.create_task(server.run(ctx))
    await wait_until(lambda: (path.exists() and stat.S_ISSOCK(path.lstat().st_mode)) or task.done())
    if task.done():
        task.result()
    try:
        yield Served(server, api, ctx, task, path)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.wait_for(task, 2.0)


async def connect(path: Path) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await asyncio.open_unix_connection(str(path))


async def ask(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, raw: bytes) -> Any:
    writer.write(raw)
    await writer.drain()
    return json.loads(await asyncio.wait_for(reader.readline(), 2.0))


async def assert_closed_by_server(reader: asyncio.StreamReader, within_s: float = 1.0) -> None:
    assert await asyncio.wait_for(reader.read(), within_s) == b""


# ---------------------------------------------------------------- round trips


async def test_status_and_commands_round_trip_and_every_command_is_logged(
    short_tmp: Path,
) -> None:
    path = short_tmp / "control.sock"
    async with serving(path, FakeApi(refuse=("engage",))) as served:
        with capture_logs() as logs:
            reply = await query(path, {"op": "status"})
            assert reply["ok"] is True
            assert reply["status"]["mode"] == "speed_hold"
            # Infinity is not JSON: it travels as null.
            assert reply["status"]["inputs"]["scan.left"]["age_s"] is None
            async with ControlClient(path) as client:
                assert await client.command("engage") == {
                    "ok": True,
                    "accepted": False,
                    "message": "engage refused: not READY",
                }
                assert await client.command("estop") == {
                    "ok": True,
                    "accepted": True,
                    "message": "estop done",
                }
                assert (await client.status())["ok"] is True
        assert served.api.requests == ["engage", "estop"]
        commands = [entry for entry in logs if entry["event"] == "control_command"]
        assert [(c["command"], c["verdict"]) for c in commands] == [
            ("engage", "refused"),
            ("estop", "accepted"),
        ]
        assert all(c["peer_uid"] == os.getuid() and c["peer_pid"] == os.getpid() for c in commands)


async def test_a_route_is_selected_through_the_socket_and_logged(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served:
        with capture_logs() as logs:
            assert await query(path, {"op": "route", "select": "north-loop"}) == {
                "ok": True,
                "accepted": True,
                "message": "route 'north-loop' selected",
            }
            refused = await query(path, {"op": "route", "select": "missing"})
            assert refused["accepted"] is False and "no such route" in refused["message"]
            bad = await query(path, {"op": "route", "select": ""})
            assert bad["ok"] is False and "route name" in bad["error"]
        assert served.api.requests == ["route:north-loop", "route:missing"]
        verdicts = [(e["route"], e["verdict"]) for e in logs if e["event"] == "route_select"]
        assert verdicts == [("north-loop", "accepted"), ("missing", "refused")]


async def test_requests_sent_together_get_one_reply_each_in_order(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served:
        reader, writer = await connect(path)
        writer.write(b'{"op":"command","name":"hold"}\n{"op":"status"}\n{"op":"bad"}\n')
        replies = [json.loads(await asyncio.wait_for(reader.readline(), 2.0)) for _ in range(3)]
        assert replies[0]["accepted"] is True
        assert "status" in replies[1]
        assert replies[2]["ok"] is False
        writer.close()
        assert served.api.requests[0] == "hold"


# ---------------------------------------------------------------- binding


async def test_socket_has_mode_0660_and_its_missing_parent_is_created_0750(
    short_tmp: Path,
) -> None:
    path = short_tmp / "run" / "dbw" / "control.sock"
    async with serving(path):
        assert stat.S_ISSOCK(path.lstat().st_mode)
        assert stat.S_IMODE(path.stat().st_mode) == 0o660
        assert stat.S_IMODE(path.parent.stat().st_mode) == 0o750
        assert (await query(path, {"op": "status"}))["ok"] is True


def current_umask() -> int:
    umask = os.umask(0o077)
    os.umask(umask)
    return umask


async def test_the_socket_is_never_open_to_others_not_even_before_its_chmod(
    short_tmp: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = short_tmp / "control.sock"
    modes_before_chmod: list[int] = []
    real_chmod = os.chmod

    def spy(target: Any, mode: int, **kw: Any) -> None:
        if stat.S_ISSOCK(os.lstat(target).st_mode):
            modes_before_chmod.append(stat.S_IMODE(os.lstat(target).st_mode))
        real_chmod(target, mode, **kw)

    umask = current_umask()
    monkeypatch.setattr(os, "chmod", spy)
    async with serving(path, mode=0o600):
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert len(modes_before_chmod) == 1
    assert modes_before_chmod[0] & 0o077 == 0, oct(modes_before_chmod[0])
    assert current_umask() == umask  # the process umask is restored


async def test_stale_socket_from_a_crashed_daemon_is_replaced(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    crashed = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    crashed.bind(str(path))
    crashed.close()  # the file stays, nobody listens
    stale_inode = path.lstat().st_ino
    with capture_logs() as logs:
        async with serving(path):
            assert (await query(path, {"op": "status"}))["ok"] is True
    assert any(entry["event"] == "control_socket_stale_removed" for entry in logs)
    assert not path.exists() or path.lstat().st_ino != stale_inode


@pytest.mark.parametrize("kind", ["file", "symlink", "directory"])
async def test_something_else_at_the_path_is_refused_and_left_alone(
    short_tmp: Path, kind: str
) -> None:
    path = short_tmp / "control.sock"
    target = short_tmp / "notes.txt"
    target.write_text("a user's file\n")
    if kind == "file":
        path.write_text("a user's file\n")
    elif kind == "symlink":
        path.symlink_to(target)
    else:
        path.mkdir()
    with pytest.raises(PermanentServiceError, match="not a socket"):
        await asyncio.wait_for(ControlServer(path, FakeApi()).run(FakeContext()), 2.0)
    if kind == "directory":
        assert path.is_dir()
    else:
        assert path.read_text() == "a user's file\n"
    assert target.read_text() == "a user's file\n"


async def test_a_second_server_on_a_live_socket_fails_permanently(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as first:
        with pytest.raises(PermanentServiceError, match="already serving"):
            await asyncio.wait_for(ControlServer(path, FakeApi()).run(FakeContext()), 2.0)
        assert not first.task.done()
        assert (await query(path, {"op": "status"}))["ok"] is True


async def test_a_path_too_long_for_a_unix_socket_fails_permanently(short_tmp: Path) -> None:
    path = short_tmp / ("x" * 120) / "control.sock"
    with pytest.raises(PermanentServiceError, match=r"paths\.control_socket"):
        await asyncio.wait_for(ControlServer(path, FakeApi()).run(FakeContext()), 2.0)


async def test_a_removed_socket_file_ends_the_run_so_the_supervisor_rebinds(
    short_tmp: Path,
) -> None:
    path = short_tmp / "control.sock"
    server = ControlServer(path, FakeApi())
    task = asyncio.create_task(server.run(FakeContext()))
    await wait_until(path.exists)
    path.unlink()
    with pytest.raises(RuntimeError, match="removed or replaced"):
        await asyncio.wait_for(task, 1.0)


# ---------------------------------------------------------------- bad clients


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        (b"{not json\n", "not valid JSON"),
        (b"[1, 2]\n", "must be a JSON object"),
        (b'"status"\n', "must be a JSON object"),
        (b"\n", "empty request"),
        (b"\xff\xfe\xfd\n", "not UTF-8"),
        (b"[" * 5000 + b"\n", "not valid JSON"),
        (b'{"name": "engage"}\n', "missing 'op': known ops are status, command"),
        (b'{"op": "reboot"}\n', "unknown op 'reboot': known ops are status, command"),
        (b'{"op": "maneuver", "step": "pot-map"}\n', "maneuver needs 'action'"),
        (b'{"op": "maneuver", "action": "go", "step": "x"}\n', "maneuver needs 'action'"),
        (b'{"op": "maneuver", "action": "start", "step": ""}\n', "maneuver needs 'step'"),
        (b'{"op": "maneuver", "action": "start"}\n', "maneuver needs 'step'"),
        (b'{"op": "samples"}\n', "samples needs 'since'"),
        (b'{"op": "samples", "since": -1}\n', "samples needs 'since'"),
        (b'{"op": "samples", "since": true}\n', "samples needs 'since'"),
        (b'{"op": "samples", "since": 1.5}\n', "samples needs 'since'"),
        (b'{"op": "samples", "since": 0, "limit": 0}\n', "samples 'limit' must be"),
        (b'{"op": "samples", "since": 0, "limit": 100000}\n', "samples 'limit' must be"),
        (b'{"op": "status", "verbose": true}\n', "unknown field(s) for op 'status': 'verbose'"),
        (b'{"op": "command"}\n', "missing command 'name'"),
        (b'{"op": "command", "name": "launch"}\n', "unknown command 'launch'"),
        (b'{"op": "command", "name": 7}\n', "unknown command 7"),
        (b'{"op": "command", "name": "engage", "speed_mps": 9}\n', "'speed_mps'"),
    ],
)
async def test_a_bad_request_gets_an_error_and_the_connection_still_answers(
    short_tmp: Path, line: bytes, expected: str
) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served:
        reader, writer = await connect(path)
        reply = await ask(reader, writer, line)
        assert reply["ok"] is False
        assert expected in reply["error"]
        if "unknown command" in expected or "missing command" in expected:
            assert all(name in reply["error"] for name in COMMAND_NAMES)
        reply = await ask(reader, writer, b'{"op": "status"}\n')
        assert reply == {"ok": True, "status": json.loads(encode_message(STATUS_DOC))}
        writer.close()
        assert served.api.requests == []  # nothing malformed reaches the vehicle


async def test_an_oversized_line_gets_an_error_and_the_connection_is_closed(
    short_tmp: Path,
) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served:
        # Exactly at the limit is still a request.
        request = b'{"op": "status"}'
        reader, writer = await connect(path)
        reply = await ask(reader, writer, request + b" " * (MAX_LINE_BYTES - len(request)) + b"\n")
        assert reply["ok"] is True
        writer.close()

        reader, writer = await connect(path)
        writer.write(b'{"op": "command", "name": "' + b"e" * (2 * MAX_LINE_BYTES))
        reply = json.loads(await asyncio.wait_for(reader.readline(), 2.0))
        assert reply["ok"] is False
        assert str(MAX_LINE_BYTES) in reply["error"]
        await assert_closed_by_server(reader)
        writer.close()
        assert served.api.requests == []
        assert (await query(path, {"op": "status"}))["ok"] is True


async def test_the_ninth_client_is_refused_and_a_freed_slot_is_reused(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served:
        clients = [await connect(path) for _ in range(8)]
        for reader, writer in clients:
            assert (await ask(reader, writer, b'{"op": "status"}\n'))["ok"] is True
        reader, writer = await connect(path)
        reply = json.loads(await asyncio.wait_for(reader.readline(), 2.0))
        assert reply["ok"] is False
        assert "too many clients" in reply["error"]
        await assert_closed_by_server(reader)
        writer.close()
        # A client gives up its slot; the next one gets in.
        clients[0][1].close()
        await wait_until(lambda: served.server.client_count == 7)
        assert (await query(path, {"op": "status"}))["ok"] is True
        for _, writer in clients[1:]:
            writer.close()


async def test_an_idle_client_is_closed_and_a_busy_one_is_not(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    async with serving(path, idle_timeout_s=0.3):
        busy_reader, busy_writer = await connect(path)
        idle_reader, idle_writer = await connect(path)
        for _ in range(5):  # 0.5 s of activity on one connection, silence on the other
            assert (await ask(busy_reader, busy_writer, b'{"op": "status"}\n'))["ok"] is True
            await asyncio.sleep(0.1)
        reply = json.loads(await asyncio.wait_for(idle_reader.readline(), 1.0))
        assert reply["ok"] is False
        assert "no request for 0.3 s" in reply["error"]
        await assert_closed_by_server(idle_reader)
        assert (await ask(busy_reader, busy_writer, b'{"op": "status"}\n'))["ok"] is True
        busy_writer.close()
        idle_writer.close()


async def test_clients_that_vanish_mid_request_do_not_affect_the_server(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served:
        _, writer = await connect(path)
        writer.write(b'{"op": "command", "na')
        await writer.drain()
        writer.close()

        _, writer = await connect(path)
        writer.write(b'{"op": "status"')
        await writer.drain()
        writer.transport.abort()  # a reset, not a clean close

        # Asks and leaves without reading the (large) reply.
        _, writer = await connect(path)
        writer.write(b'{"op": "status"}\n' * 200)
        await writer.drain()
        writer.transport.abort()

        await wait_until(lambda: served.server.client_count == 0)
        assert not served.task.done()
        assert (await query(path, {"op": "status"}))["ok"] is True
        assert served.api.requests == []


async def test_a_hold_is_released_when_its_connection_drops(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served:
        async with ControlClient(path) as client:
            assert (await client.command("hold"))["accepted"] is True
        await wait_until(lambda: served.api.requests == ["hold", "release"])

        async with ControlClient(path) as client:  # released properly: nothing more
            await client.command("hold")
            await client.command("release")
        await wait_until(lambda: served.server.client_count == 0)
        assert served.api.requests == ["hold", "release", "hold", "release"]


async def test_a_pedal_sweep_is_disarmed_when_its_connection_drops(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    start = {"op": "maneuver", "action": "start", "step": "pedals"}
    async with serving(path) as served:
        async with ControlClient(path) as client:
            assert (await client.call(start))["accepted"] is True
        await wait_until(
            lambda: served.api.requests == ["maneuver:start:pedals", "maneuver:stop:pedals"]
        )
        served.api.requests.clear()
        async with ControlClient(path) as client:  # a resumed one likewise
            await client.call({"op": "maneuver", "action": "start", "step": "pedals@2"})
        await wait_until(
            lambda: served.api.requests == ["maneuver:start:pedals@2", "maneuver:stop:pedals"]
        )
        served.api.requests.clear()
        async with ControlClient(path) as client:  # stopped properly, or another step
            await client.call(start)
            await client.call({"op": "maneuver", "action": "stop", "step": "pedals"})
            await client.call({"op": "maneuver", "action": "start", "step": "pot-map"})
        await wait_until(lambda: served.server.client_count == 0)
        assert served.api.requests == [
            "maneuver:start:pedals",
            "maneuver:stop:pedals",
            "maneuver:start:pot-map",
        ]


async def test_a_failing_daemon_api_costs_one_reply_not_the_connection(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    api = FakeApi()
    api.fail_status = api.fail_request = True
    async with serving(path, api):
        reader, writer = await connect(path)
        reply = await ask(reader, writer, b'{"op": "status"}\n')
        assert reply["ok"] is False
        assert "status exploded" in reply["error"]
        reply = await ask(reader, writer, b'{"op": "command", "name": "engage"}\n')
        assert reply["ok"] is False
        assert "request exploded" in reply["error"]
        api.fail_status = False
        assert (await ask(reader, writer, b'{"op": "status"}\n'))["ok"] is True
        writer.close()


# ---------------------------------------------------------------- lifecycle


async def test_cancelling_run_closes_clients_promptly_and_removes_the_socket(
    short_tmp: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = short_tmp / "control.sock"
    server = ControlServer(path, FakeApi())
    task = asyncio.create_task(server.run(FakeContext()))
    await wait_until(path.exists)
    quiet_reader, quiet_writer = await connect(path)
    partial_reader, partial_writer = await connect(path)
    partial_writer.write(b'{"op": "sta')
    await partial_writer.drain()
    await wait_until(lambda: server.client_count == 2)

    started_s = time.monotonic()
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await asyncio.wait_for(task, 1.0)
    assert time.monotonic() - started_s < 0.5
    assert not path.exists()
    await assert_closed_by_server(quiet_reader, within_s=0.5)
    await assert_closed_by_server(partial_reader, within_s=0.5)
    assert server.client_count == 0
    quiet_writer.close()
    partial_writer.close()
    # Clients are hung up on, not cancelled (Python 3.11 logs a cancelled handler as an
    # unhandled error), and nothing else went wrong on the way out.
    await asyncio.sleep(0.01)
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


async def test_run_beats_at_least_every_200_ms_while_serving(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served:
        await asyncio.sleep(0.6)
        beats = list(served.ctx.beats)
    assert len(beats) >= 4
    assert max(b - a for a, b in itertools.pairwise(beats)) <= 0.2


# ---------------------------------------------------------------- the client's errors


async def test_query_explains_a_missing_socket_and_a_dead_one(short_tmp: Path) -> None:
    with pytest.raises(ControlSocketError, match=r"is the daemon running\? `systemctl status dbw`"):
        await query(short_tmp / "nope.sock", {"op": "status"})
    dead = short_tmp / "dead.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(dead))
    sock.close()
    with pytest.raises(ControlSocketError, match="nobody is listening"):
        await query(dead, {"op": "status"})


async def test_query_explains_a_daemon_that_does_not_answer_or_hangs_up(short_tmp: Path) -> None:
    async def mute(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read()  # until the client gives up
        writer.close()

    async def rude(_: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.close()

    for name, handler, expected in (
        ("mute.sock", mute, "no reply from the daemon within 0.2 s"),
        ("rude.sock", rude, "closed the connection before replying"),
    ):
        server = await asyncio.start_unix_server(handler, str(short_tmp / name))
        try:
            with pytest.raises(ControlSocketError, match=expected):
                await query(short_tmp / name, {"op": "status"}, timeout_s=0.2)
        finally:
            server.close()
            await server.wait_closed()


async def test_query_explains_permission_denied(short_tmp: Path) -> None:
    """As a user: a locked directory. As root (which bypasses permissions): the check is
    run by a child that drops to nobody, against the 0660 root-owned socket itself."""
    if os.geteuid() != 0:
        locked = short_tmp / "locked"
        async with serving(locked / "control.sock"):
            locked.chmod(0o000)
            with pytest.raises(ControlSocketError, match="you need to be in the dbw group"):
                await query(locked / "control.sock", {"op": "status"})
            locked.chmod(0o750)
        return
    public = short_tmp / "public"
    public.mkdir()
    async with serving(public / "control.sock"):
        os.chmod(short_tmp, 0o755)
        os.chmod(public, 0o755)  # nobody may reach the socket; only its mode keeps them out
        child = textwrap.dedent(
            f"""
            import os
            from appliance.control_client import query_sync
            from appliance.control_protocol import ControlSocketError
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            try:
                query_sync({str(public / "control.sock")!r}, {{"op": "status"}})
            except ControlSocketError as exc:
                print(exc)
            else:
                print("no error")
            """
        )
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-c", child, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        out, err = await asyncio.wait_for(proc.communicate(), 10)
    assert proc.returncode == 0, err.decode()
    assert "you need to be in the dbw group (or root)" in out.decode()


# ---------------------------------------------------------------- the protocol core


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200) | st.text(max_size=200).map(str.encode))
def test_decode_request_parses_or_raises_request_error(line: bytes) -> None:
    try:
        request = decode_request(line)
    except RequestError:
        return
    assert isinstance(
        request, StatusRequest | CommandRequest | RouteRequest | ManeuverRequest | SamplesRequest
    )


def test_decode_request_accepts_exactly_the_protocol() -> None:
    assert decode_request(b'{"op": "status"}\n') == StatusRequest()
    for name in COMMAND_NAMES:
        line = json.dumps({"op": "command", "name": name}).encode()
        assert decode_request(line) == CommandRequest(name)
    assert decode_request(b'{"op": "maneuver", "action": "stop", "step": "pedals"}') == (
        ManeuverRequest("stop", "pedals")
    )
    assert decode_request(b'{"op": "samples", "since": 7}') == SamplesRequest(7)
    assert decode_request(b'{"op": "samples", "since": 0, "limit": 5}') == SamplesRequest(0, 5)


async def test_a_maneuver_is_started_and_its_samples_read_through_the_socket(
    short_tmp: Path,
) -> None:
    path = short_tmp / "control.sock"
    async with serving(path) as served, ControlClient(path) as client:
        started = await client.call({"op": "maneuver", "action": "start", "step": "pot-map"})
        assert started == {"ok": True, "accepted": True, "message": "start pot-map"}
        refused = await client.call({"op": "maneuver", "action": "start", "step": "warp"})
        assert refused["accepted"] is False and "warp" in refused["message"]
        reply = await client.call({"op": "samples", "since": 4, "limit": 2})
        assert reply["ok"] is True and reply["missed"] == 6 and reply["next"] == 12
        assert [s["seq"] for s in reply["samples"]] == [10, 11]
        assert served.api.requests == [
            "maneuver:start:pot-map",
            "maneuver:start:warp",
            "samples:4:2",
        ]


def test_encode_message_is_strict_json_on_one_line() -> None:
    line = encode_message({"a": float("nan"), "b": [float("-inf"), (1, 2)], "c": "x\ny", 3: {1}})
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    assert json.loads(line) == {"a": None, "b": [None, [1, 2]], "c": "x\ny", "3": [1]}


# ---------------------------------------------------------------- the `dbw` commands


@pytest.fixture
def server_logs() -> io.StringIO:
    """The server's logs, kept out of the output of the commands run in this process."""
    stream = io.StringIO()
    configure_logging("debug", stream=stream, json=True)
    return stream


async def invoke(command: Any, *args: str) -> Any:
    """Run a click command as `dbw` would, in a thread: it has an event loop of its own."""
    return await asyncio.to_thread(CliRunner().invoke, command, list(args))


async def test_cli_status_prints_the_human_view_and_json(
    short_tmp: Path, server_logs: io.StringIO
) -> None:
    path = short_tmp / "control.sock"
    async with serving(path):
        result = await invoke(status, "--socket", str(path))
        assert result.exit_code == 0, result.output
        assert result.stdout.startswith("SPEED_HOLD for 12.3 s")
        assert "critical input stale: scan.left" in result.stdout

        result = await invoke(status, "--socket", str(path), "--json")
        assert result.exit_code == 0, result.output
        assert json.loads(result.stdout) == json.loads(encode_message(STATUS_DOC))

        result = await invoke(status, "--socket", str(path), "--watch", "0.1", "--count", "3")
        assert result.exit_code == 0, result.output
        assert result.stdout.count("SPEED_HOLD for") == 3


async def test_cli_commands_exit_0_when_accepted_and_1_with_the_reasons_when_refused(
    short_tmp: Path,
    server_logs: io.StringIO,
) -> None:
    path = short_tmp / "control.sock"
    async with serving(path, FakeApi(refuse=("speed_plus",))) as served:
        result = await invoke(engage, "--socket", str(path))
        assert result.exit_code == 0, result.output
        assert "engage: accepted: engage done" in result.stdout

        result = await invoke(speed_up, "--socket", str(path))
        assert result.exit_code == 1, result.output
        assert "speed_plus: refused: speed_plus refused: not READY" in result.stderr
        assert "  - critical input stale: scan.left" in result.stderr
        assert served.api.requests == ["engage", "speed_plus"]


async def test_cli_exits_2_when_it_cannot_talk_to_the_daemon(
    short_tmp: Path, server_logs: io.StringIO
) -> None:
    for command in CONTROL_COMMANDS:
        result = await invoke(command, "--socket", str(short_tmp / "none.sock"))
        assert result.exit_code == 2, (command.name, result.output)
        assert "is the daemon running?" in result.stderr
        assert "Traceback" not in result.output
        if command.name == "estop":
            assert "THE E-STOP WAS NOT SENT" in result.stderr
    result = await invoke(status, "--config", str(short_tmp / "missing.toml"))
    assert result.exit_code == 2
    assert "no such file" in result.stderr


async def test_cli_takes_the_socket_from_the_config(
    short_tmp: Path, server_logs: io.StringIO
) -> None:
    path = short_tmp / "from-config.sock"
    config = short_tmp / "vehicle.toml"
    config.write_text(f'[simulation]\nenabled = true\n[paths]\ncontrol_socket = "{path}"\n')
    async with serving(path):
        result = await invoke(status, "--config", str(config))
        assert result.exit_code == 0, result.output
        assert "SPEED_HOLD" in result.stdout


async def test_cli_hold_presses_for_the_given_time_then_releases(
    short_tmp: Path, server_logs: io.StringIO
) -> None:
    path = short_tmp / "control.sock"
    async with serving(path, FakeApi(refuse=())) as served:
        started_s = time.monotonic()
        result = await invoke(hold, "--socket", str(path), "--seconds", "0.6")
        assert result.exit_code == 0, result.output
        assert time.monotonic() - started_s >= 0.6
        assert served.api.requests == ["hold", "release"]
        assert "holding for 0.6 s (Ctrl-C releases)" in result.stdout
        assert len(re.findall(r"^holding +[0-9.]+/0.6 s  SPEED_HOLD", result.stdout, re.M)) == 2
        assert "release: accepted" in result.stdout

    async with serving(path, FakeApi(refuse=("hold",))) as served:
        result = await invoke(hold, "--socket", str(path), "--seconds", "5")
        assert result.exit_code == 1
        assert "hold: refused" in result.stderr
        assert served.api.requests == ["hold"]


async def test_cli_hold_releases_on_ctrl_c(short_tmp: Path) -> None:
    path = short_tmp / "control.sock"
    # Ctrl-C as a terminal delivers it (tests/conftest.py: the child starts with Python's
    # own SIGINT handler even when the suite runs as a background job).
    child = "from appliance.cli.control import hold; hold()"
    async with serving(path) as served:
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            "-c",
            child,
            "--socket",
            str(path),
            "--seconds",
            "30",
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        assert proc.stdout is not None
        line = await asyncio.wait_for(proc.stdout.readline(), 10)
        assert b"hold: accepted" in line
        await wait_until(lambda: served.api.requests == ["hold"])
        proc.send_signal(signal.SIGINT)
        out, err = await asyncio.wait_for(proc.communicate(), 5)
        assert served.api.requests == ["hold", "release"]
        assert proc.returncode == 0, err.decode()
        assert b"release: accepted" in out
        assert b"Traceback" not in err


def test_control_commands_are_the_documented_ones() -> None:
    assert [command.name for command in CONTROL_COMMANDS] == [
        "status",
        "engage",
        "disengage",
        "speed-up",
        "speed-down",
        "estop",
        "estop-reset",
        "hold",
    ]


def test_query_sync_works_without_an_event_loop(short_tmp: Path) -> None:
    with pytest.raises(ControlSocketError, match="is the daemon running"):
        query_sync(short_tmp / "none.sock", {"op": "status"})
