"""The bench's Unix socket: newline-delimited JSON, one reply per request.

The same framing as the daemon's control socket (:mod:`appliance.control_protocol`), so
``appliance.control_client.ControlClient`` talks to it as well. The socket is made
readable and writable by its owner only; the daemon puts it in the simulated vehicle's
private directory (``mkdtemp``, mode 0700). A line that is not JSON, too long, or not a
request gets an error reply; a connection that sends more than a line's worth without a
newline is closed. Nothing a client sends can stop the simulated vehicle.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import stat
from pathlib import Path
from typing import Any

from appliance.control_protocol import MAX_LINE_BYTES, encode_message, error_reply
from appliance.logs import get_logger
from appliance.sim.bench import SimBench

log = get_logger("sim.bench")


class BenchSocketError(RuntimeError):
    """The bench socket cannot be made at the path given."""


async def serve_bench(path: str | Path, bench: SimBench) -> asyncio.Server:
    """Listen on ``path`` for bench requests until the returned server is closed."""
    path = str(path)
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        pass
    else:
        if not stat.S_ISSOCK(info.st_mode):
            raise BenchSocketError(f"{path}: exists and is not a socket; not replacing it")
        os.unlink(path)  # a socket left by a simulated vehicle that was killed

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await _converse(bench, reader, writer)

    try:
        server = await asyncio.start_unix_server(serve, path, limit=MAX_LINE_BYTES)
    except OSError as exc:
        raise BenchSocketError(f"{path}: cannot listen: {exc.strerror or exc}") from None
    os.chmod(path, 0o600)
    log.info("bench_listening", path=path)
    return server


async def _converse(
    bench: SimBench, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
) -> None:
    try:
        while True:
            try:
                line = await reader.readuntil(b"\n")
            except asyncio.IncompleteReadError:
                return  # the client hung up (a partial last line is not a request)
            except asyncio.LimitOverrunError:
                too_long = error_reply(f"request longer than {MAX_LINE_BYTES} bytes")
                writer.write(encode_message(too_long))
                return
            try:
                message = json.loads(line)
            except (UnicodeDecodeError, ValueError, RecursionError) as exc:
                reply = error_reply(f"request is not valid JSON: {exc}")
            else:
                reply = await _handle(bench, message)
            writer.write(encode_message(reply))
            await writer.drain()
    except ConnectionError:
        return
    finally:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


async def _handle(bench: SimBench, message: object) -> dict[str, Any]:
    """The bench's reply; an action that fails on the twins is an error reply, not a crash."""
    try:
        return await bench.handle(message)
    except Exception as exc:  # a twin refused: say so, keep serving
        log.warning("bench_action_failed", request=str(message)[:200], error=repr(exc))
        return error_reply(f"the simulated vehicle could not do that: {exc!r}")
