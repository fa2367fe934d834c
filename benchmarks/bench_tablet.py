"""The tablet's hold button let go, or its link dropped: how long until the stop is sent.

The daemon on the simulated forklift with its tablet page on 127.0.0.1 (in this process,
as `dbw run` would run it). A client pairs, holds the button (a beat every 0.1 s over
HTTP, as the page does), and raises the set speed until the vehicle drives; then either
releases it (an explicit ``held: false``) or stops beating (a frozen page, a dropped
link). Measured: from the release's request leaving the client, or from the last beat's
answer, to the first control output after it whose speed command to the PC104 is lower
than the one before (the hold-to-move stop begun, the command having been steady at the
set speed; timestamped as the loop hands it to the sinks, on its way to the wire). The
figure to compare with: one control cycle (release), one cycle plus the configured hold
timeout (dropped link).

Run: ``python -m benchmarks.bench_tablet [REPEATS]`` (20 of each by default).
"""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from appliance.config import load_config
from appliance.config.models import VehicleConfig
from appliance.core.output import CoreOutput
from appliance.daemon import Daemon
from appliance.modes import Mode
from benchmarks.stats import summarize

BEAT_S = 0.1


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _config() -> VehicleConfig:
    config = load_config("forklift-sim")
    devices = config.devices.model_copy(
        update={
            side: getattr(config.devices, side).model_copy(update={"port": _free_port()})
            for side in ("lms111_left", "lms111_right")
        }
    )
    tablet = config.tablet_page.model_copy(update={"enabled": True, "port": 0})
    # The release's path to the wire, on a source that is always ready to move.
    engagement = config.engagement.model_copy(update={"autopilot_source": "hold_straight"})
    return config.model_copy(
        update={"devices": devices, "tablet_page": tablet, "engagement": engagement}
    )


async def _post(port: int, path: str, body: dict[str, Any], token: str | None) -> dict[str, Any]:
    data = json.dumps(body).encode()
    head = f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: {len(data)}\r\n"
    if token is not None:
        head += f"Authorization: Bearer {token}\r\n"
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(head.encode() + b"\r\n" + data)
    await writer.drain()
    response = await reader.read()
    writer.close()
    payload = response.partition(b"\r\n\r\n")[2]
    document: dict[str, Any] = json.loads(payload) if payload.startswith(b"{") else {}
    return document


class Outputs:
    """Every control output with the time it went to the sinks."""

    def __init__(self) -> None:
        self.log: list[tuple[float, float, Mode]] = []

    def __call__(self, output: CoreOutput) -> None:
        self.log.append((time.monotonic(), output.pc104.speed_mps, output.mode))

    def first_slower_after(self, t_s: float) -> float | None:
        """The first output after ``t_s`` whose speed command is below the one before
        it: the stop has begun (the set speed reached, the command was steady)."""
        for (_, before, _), (when, speed, _) in zip(self.log, self.log[1:], strict=False):
            if when >= t_s and speed < before - 1e-6:
                return when
        return None


async def _measure(repeats: int) -> tuple[list[float], list[float]]:
    config = _config()
    directory = tempfile.mkdtemp(prefix="dbw-bench-", dir="/tmp")
    daemon = Daemon(config, control_socket=str(Path(directory) / "control.sock"), record=False)
    outputs = Outputs()
    daemon.control.on_output.append(outputs)
    run = asyncio.ensure_future(daemon.run(handle_signals=False))
    released: list[float] = []
    dropped: list[float] = []
    seq = 0
    try:
        assert daemon.tablet is not None
        service = daemon.tablet
        deadline = time.monotonic() + 60.0
        while daemon.core.state.mode is not Mode.READY or service.page.bound_port is None:
            if time.monotonic() > deadline:
                raise SystemExit("the daemon did not get READY")
            await asyncio.sleep(0.05)
        port = service.page.bound_port
        token = (await _post(port, "/api/pair", {"code": service.gate.code}, None))["token"]

        async def beat(held: bool) -> None:
            nonlocal seq
            seq += 1
            await _post(port, "/api/hold", {"seq": seq, "held": held}, token)

        for round_index in range(2 * repeats):
            # Held: engaged, speed hold; the set speed raised until it drives at 0.4 m/s.
            for _ in range(10):
                await beat(True)
                await asyncio.sleep(BEAT_S)
            for _ in range(4):
                daemon.core.request("speed_plus", daemon.clock())
                await beat(True)
                await asyncio.sleep(BEAT_S)
            for _ in range(30):  # 3 s: the command up at the set speed, steady
                await beat(True)
                await asyncio.sleep(BEAT_S)
            if round_index % 2 == 0:
                sent = time.monotonic()
                await beat(False)
                await asyncio.sleep(0.2)
                stop = outputs.first_slower_after(sent)
                if stop is not None:
                    released.append(stop - sent)
            else:
                await beat(True)
                last_answer = time.monotonic()
                await asyncio.sleep(config.tablet_page.hold_timeout_s + 0.3)
                stop = outputs.first_slower_after(last_answer)
                if stop is not None:
                    dropped.append(stop - last_answer)
            # Stand still, released, before the next round (speed hold stays set).
            await asyncio.sleep(2.5)
            daemon.core.request("disengage", daemon.clock())
            await asyncio.sleep(0.5)
    finally:
        daemon.request_stop("benchmark over")
        await asyncio.wait_for(run, 15.0)
        shutil.rmtree(directory, ignore_errors=True)
    return released, dropped


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    repeats = int(args[0]) if args else 20
    released, dropped = asyncio.run(_measure(repeats))
    config = _config()
    cycle_ms = 1e3 / config.rates.control_hz
    timeout_ms = config.tablet_page.hold_timeout_s * 1e3
    print(f"the simulated forklift, {repeats} releases and {repeats} dropped links")
    print(f"  one control cycle: {cycle_ms:.0f} ms; hold timeout: {timeout_ms:.0f} ms")
    print("  " + summarize("release -> stop sent", [t * 1e3 for t in released], "ms"))
    print("  " + summarize("dropped link -> stop sent", [t * 1e3 for t in dropped], "ms"))
    drop_ms = cycle_ms + timeout_ms
    print(f"  (the figure: release within {cycle_ms:.0f} ms, a drop within {drop_ms:.0f} ms)")


if __name__ == "__main__":
    main()
