"""Actuator board links: 4 boards x 100 Hz telemetry, latency from twin write to topic update.

Two set-ups. *Separate process*: the twins run in their own process, as the boards are their
own microcontrollers, so the figure is the host's cost alone (kernel pty hop, event-loop
wake-up, decode, publish). *Same process*: the twins share the daemon's event loop, as in
``dbw run --config sim``; their own work then delays the host's reads, which is the figure a
simulation run sees. Latency pairs each telemetry frame's write time (recorded by the twin
with ``time.monotonic``, which is system-wide) with the moment the client published it,
matched by the frame's sequence number. Target: p99 < 2 ms, CRC errors 0.
"""

from __future__ import annotations

import asyncio
import bisect
import multiprocessing
import os
import time
from collections import defaultdict
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any, TypeVar

from appliance.config import load_config
from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from benchmarks.stats import summarize
from drivers.actuators.client import ActuatorClient
from drivers.actuators.messages import (
    BrakeCommand,
    BrakeTelemetry,
    PanelCommand,
    PanelTelemetry,
    SteeringCommand,
    SteeringMode,
    SteeringTelemetry,
    Telemetry,
    ThrottleCommand,
    ThrottleTelemetry,
)
from drivers.actuators.protocol import ActuatorCodec
from drivers.topics import Sample, Topic

T = TypeVar("T")
DURATION_S = 4.0
TxLogs = dict[str, list[tuple[int, float]]]


class TimingTopic(Topic[T]):
    """A topic that notes (frame seq, publish time) and the read-to-publish time per sample."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.codec: ActuatorCodec | None = None
        self.log: list[tuple[int, float]] = []
        self.read_to_publish_ms: list[float] = []

    def publish(self, value: T, stamp_s: float) -> Sample[T]:
        sample = super().publish(value, stamp_s)
        now_s = time.monotonic()
        assert self.codec is not None and self.codec.last_received_seq is not None
        self.log.append((self.codec.last_received_seq, now_s))
        self.read_to_publish_ms.append((now_s - stamp_s) * 1e3)
        return sample


def _make_twins() -> ActuatorTwins:
    world = SimWorld(VehicleParams.from_config(load_config("sim")))
    twins = ActuatorTwins(world)
    for twin in twins.boards.values():
        twin.tx_clock = time.monotonic
    return twins


def _twin_process(conn: Connection, duration_s: float) -> None:
    """Child process: the four boards, paced in real time, reporting their write times."""

    async def serve() -> None:
        twins = _make_twins()
        conn.send({name: twins.port_path(f"sim://{name}") for name in twins.boards})
        task = asyncio.create_task(twins.run())
        await asyncio.get_running_loop().run_in_executor(None, conn.recv)  # "go"
        for twin in twins.boards.values():
            twin.tx_log.clear()
        cpu_s, wall_s = time.process_time(), time.monotonic()
        await asyncio.sleep(duration_s)
        cpu_pct = 100 * (time.process_time() - cpu_s) / (time.monotonic() - wall_s)
        task.cancel()
        conn.send({"tx": {n: t.tx_log for n, t in twins.boards.items()}, "cpu_pct": cpu_pct})
        twins.close()

    asyncio.run(serve())


def _clients(paths: dict[str, str]) -> dict[str, ActuatorClient[Any]]:
    kinds: dict[str, type[Telemetry]] = {
        "steering": SteeringTelemetry,
        "throttle": ThrottleTelemetry,
        "brake": BrakeTelemetry,
        "panel": PanelTelemetry,
    }
    clients: dict[str, ActuatorClient[Any]] = {}
    for name, kind in kinds.items():
        topic: TimingTopic[Any] = TimingTopic(name)
        client: ActuatorClient[Any] = ActuatorClient(kind, paths[name], topic=topic)
        topic.codec = client.codec
        clients[name] = client
    clients["steering"].set_command(SteeringCommand(SteeringMode.RELEASE))
    clients["throttle"].set_command(ThrottleCommand(False))
    clients["brake"].set_command(BrakeCommand(False))
    clients["panel"].set_command(PanelCommand())
    return clients


async def _measure(
    clients: dict[str, ActuatorClient[Any]],
    duration_s: float,
    on_start: Callable[[], None] = lambda: None,
) -> float:
    """Serve the clients for ``duration_s`` (after they are up); return their CPU %."""
    tasks = [asyncio.create_task(c.run(lambda: None)) for c in clients.values()]
    try:
        while not all(c.health().healthy for c in clients.values()):
            await asyncio.sleep(0.01)
        for client in clients.values():
            topic = client.telemetry
            assert isinstance(topic, TimingTopic)
            topic.log.clear()
            topic.read_to_publish_ms.clear()
        on_start()
        cpu_s, wall_s = time.process_time(), time.monotonic()
        await asyncio.sleep(duration_s)
        return 100 * (time.process_time() - cpu_s) / (time.monotonic() - wall_s)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


def _latencies_ms(tx: list[tuple[int, float]], rx: list[tuple[int, float]]) -> list[float]:
    """Pair each publish with the latest write of the same sequence number before it."""
    writes: dict[int, list[float]] = defaultdict(list)
    for seq, t in tx:
        writes[seq].append(t)
    out: list[float] = []
    for seq, t_rx in rx:
        times = writes.get(seq, [])
        i = bisect.bisect_right(times, t_rx)
        if i and t_rx - times[i - 1] < 1.0:
            out.append((t_rx - times[i - 1]) * 1e3)
    return out


def _report(
    title: str, clients: dict[str, ActuatorClient[Any]], tx: TxLogs, cpu: dict[str, float]
) -> list[str]:
    lines = [f"### {title}"]
    everything: list[float] = []
    decode: list[float] = []
    for name, client in clients.items():
        topic = client.telemetry
        assert isinstance(topic, TimingTopic)
        latencies = _latencies_ms(tx[name], topic.log)
        everything += latencies
        decode += topic.read_to_publish_ms
        rate_hz = len(topic.log) / DURATION_S
        lines.append(summarize(f"{name}: write -> topic ({rate_hz:.1f} Hz)", latencies, "ms"))
    lines.append(summarize("all boards: write -> topic", everything, "ms"))
    lines.append(summarize("  of which read callback -> topic (decode, publish)", decode, "ms"))
    healths = [c.health() for c in clients.values()]
    lines.append(
        f"CRC errors {sum(h.crc_errors for h in healths)}, framing errors "
        f"{sum(h.framing_errors for h in healths)}, sequence gaps "
        f"{sum(h.seq_gaps for h in healths)}, frames matched {len(everything)} of "
        f"{sum(len(v) for v in tx.values())} written"
    )
    lines.append(", ".join(f"CPU {k} {v:.1f} %" for k, v in cpu.items()) + " (of one core)")
    return lines


def bench_separate_process() -> list[str]:
    context = multiprocessing.get_context("spawn")
    ours, theirs = context.Pipe()
    child = context.Process(target=_twin_process, args=(theirs, DURATION_S), daemon=True)
    child.start()
    try:
        clients = _clients(ours.recv())

        async def go() -> float:
            async def signal_when_up() -> None:
                while not all(c.health().healthy for c in clients.values()):
                    await asyncio.sleep(0.01)
                ours.send("go")

            starter = asyncio.create_task(signal_when_up())
            cpu = await _measure(clients, DURATION_S + 0.05)
            await starter
            return cpu

        client_cpu = asyncio.run(go())
        result = ours.recv()
    finally:
        child.join(5.0)
    cpu = {"clients": client_cpu, "twins (other process)": result["cpu_pct"]}
    return _report(
        "twins in a separate process (the host's own latency)", clients, result["tx"], cpu
    )


def bench_same_process() -> list[str]:
    twins = _make_twins()
    clients = _clients({name: twins.port_path(f"sim://{name}") for name in twins.boards})

    def clear_tx_logs() -> None:
        for twin in twins.boards.values():
            twin.tx_log.clear()

    async def go() -> float:
        runner = asyncio.create_task(twins.run())
        try:
            return await _measure(clients, DURATION_S, on_start=clear_tx_logs)
        finally:
            runner.cancel()

    try:
        cpu_pct = asyncio.run(go())
        tx = {name: twin.tx_log for name, twin in twins.boards.items()}
    finally:
        twins.close()
    return _report(
        "twins in the same event loop (dbw run --config sim)",
        clients,
        tx,
        {"clients + twins": cpu_pct},
    )


def main() -> None:
    from appliance.logs import configure_logging

    configure_logging("critical", stream=open(os.devnull, "w"), json=True)  # noqa: SIM115
    print("## actuator boards (4 boards, 100 Hz telemetry each, 50 Hz commands)")
    for line in bench_separate_process() + bench_same_process():
        print(line)


if __name__ == "__main__":
    main()
