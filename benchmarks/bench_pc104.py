"""PC104 link: throughput under a loaded bus, staleness detection time, codec cost.

Figures:
* frames/s the client handles on a ``virtual`` bus carrying ~4,000 frames/s (PC104
  status at 50 Hz plus filler frames of other identifiers), whether any status frame was
  lost, and the CPU % of the process (``time.process_time`` over wall time; the process
  also runs the load generator, whose own share is measured separately and reported);
* staleness: time from the last valid status to the client reporting stale, with the
  50 Hz control period of the sim profile (limit: ``pc104_status_max_age_s`` = 100 ms);
* encode / decode / monitor cost per frame in µs.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import threading
import time
import timeit
import uuid

import can

from appliance.config import load_config, parts
from appliance.config.models import CanEndpoint
from appliance.timing import FixedRateTicker
from benchmarks.stats import summarize
from drivers.pc104 import protocol
from drivers.pc104.client import Pc104Client
from drivers.pc104.endpoint import CanInterface
from drivers.pc104.link import bus_factory
from drivers.pc104.messages import ControlSource, MotionCommand, MotionPattern, Pc104Status
from drivers.pc104.monitor import MonitorParams, ReceiveMonitor

TOTAL_FPS = 4000
BURST_S = 0.005
LOAD_SECONDS = 5.0
STATUS = Pc104Status(MotionPattern.STRAIGHT, True, ControlSource.AUTOMATIC, measured_speed_mps=1.0)
STATUS_ID = protocol.spec_for(Pc104Status).frame_id


def _frame(arbitration_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)


class LoadGenerator(threading.Thread):
    """Sends status at 50 Hz and filler traffic so the bus carries ~``total_fps`` frames/s."""

    def __init__(self, channel: str, with_status: bool = True, total_fps: int = TOTAL_FPS) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.with_status = with_status
        self.total_fps = total_fps
        self.stop_event = threading.Event()
        self.sent = self.status_sent = 0

    def run(self) -> None:
        rng = random.Random(1)
        per_burst = max(round(self.total_fps * BURST_S), 1)
        next_s = next_status_s = time.monotonic()
        counter = 0
        while not self.stop_event.is_set():
            now_s = time.monotonic()
            frames = per_burst
            if self.with_status and now_s >= next_status_s:
                arbitration_id, data = protocol.encode(STATUS, counter)
                counter = (counter + 1) % 16
                self.bus.send(_frame(arbitration_id, data))
                self.status_sent += 1
                frames -= 1
                next_status_s += 0.02
            for _ in range(frames):
                filler_id = rng.randrange(0x200, 0x700)
                self.bus.send(_frame(filler_id, rng.randbytes(8)))
            self.sent += per_burst
            while self.bus.recv(0) is not None:  # the client's commands: nobody else reads them
                pass
            next_s += BURST_S
            time.sleep(max(next_s - time.monotonic(), 0.0))
        self.bus.shutdown()


def _cpu_percent(seconds: float) -> tuple[float, float]:
    """(CPU % of the process, wall seconds) while sleeping ``seconds`` in this thread."""
    wall0, cpu0 = time.monotonic(), time.process_time()
    time.sleep(seconds)
    wall, cpu = time.monotonic() - wall0, time.process_time() - cpu0
    return 100.0 * cpu / wall, wall


async def bench_loaded_bus() -> list[str]:
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    endpoint = CanEndpoint(interface=CanInterface.VIRTUAL, channel=channel)
    # The generator alone first, to know its share of the CPU.
    alone = LoadGenerator(f"{channel}-alone")
    sink = can.Bus(interface="virtual", channel=f"{channel}-alone")
    alone.start()
    drain_stop = threading.Event()

    def drain() -> None:
        while not drain_stop.is_set():
            sink.recv(0.05)

    drainer = threading.Thread(target=drain, daemon=True)
    drainer.start()
    generator_cpu, _ = await asyncio.to_thread(_cpu_percent, 2.0)
    alone.stop_event.set()
    drain_stop.set()
    alone.join()
    drainer.join()
    sink.shutdown()

    client = Pc104Client(
        parts.pc104_client_params(load_config("sim")), endpoint, open_bus=bus_factory(endpoint)
    )
    runner = asyncio.create_task(client.run(lambda: None))
    await asyncio.sleep(0.2)
    generator = LoadGenerator(channel)
    generator.start()
    await asyncio.sleep(1.0)  # settle: resync, rate windows
    monitor = client.monitors[STATUS_ID]
    accepted0, status_sent0, sent0 = monitor.counts.accepted, generator.status_sent, generator.sent
    # A 50 Hz control loop in the same event loop as the client, as in the daemon.
    ticker = FixedRateTicker(0.02)

    async def control_loop() -> None:
        while True:
            await ticker.tick()

    control = asyncio.create_task(control_loop())
    cpu_percent, wall_s = await asyncio.to_thread(_cpu_percent, LOAD_SECONDS)
    control.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await control
    loop_report = ticker.stats.report()
    health = client.health()
    offered_fps = (generator.sent - sent0) / wall_s
    generator.stop_event.set()
    generator.join()
    await asyncio.sleep(0.1)  # let the last frames in flight arrive before counting
    accepted = monitor.counts.accepted - accepted0
    status_sent = generator.status_sent - status_sent0
    runner.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await runner
    lost = monitor.counts.lost_frames + monitor.counts.jumps
    return [
        f"loaded bus: offered {offered_fps:.0f} frames/s, client handled "
        f"{health.frames_in_per_s:.0f} frames/s in, {health.frames_out_per_s:.0f} frames/s out",
        f"loaded bus: status frames sent {status_sent}, accepted {accepted} in {wall_s:.1f} s "
        f"(counter skips {monitor.counts.skips}, lost {lost}, late {monitor.counts.late}, "
        f"stale now: {health.stale})",
        f"loaded bus: 50 Hz control loop beside the client: {loop_report.cycles} cycles, "
        f"{loop_report.overruns} missed, jitter p50 {loop_report.jitter_p50_ms:.2f} ms, "
        f"p99 {loop_report.jitter_p99_ms:.2f} ms, max {loop_report.jitter_max_ms:.2f} ms",
        f"loaded bus: CPU {cpu_percent:.1f} % of one core for the whole process "
        f"(load generator alone: {generator_cpu:.1f} %; "
        f"client ≈ {cpu_percent - generator_cpu:.1f} %)",
    ]


async def bench_staleness(trials: int = 25) -> str:
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    endpoint = CanEndpoint(interface=CanInterface.VIRTUAL, channel=channel)
    client = Pc104Client(
        parts.pc104_client_params(load_config("sim")), endpoint, open_bus=bus_factory(endpoint)
    )
    runner = asyncio.create_task(client.run(lambda: None))
    bus = can.Bus(interface="virtual", channel=channel)
    monitor = client.monitors[STATUS_ID]
    rng = random.Random(2)
    counter = 0
    detection_ms: list[float] = []
    try:
        for _ in range(trials):
            end_s = time.monotonic() + rng.uniform(0.1, 0.14)  # stop at a random phase
            while time.monotonic() < end_s or client.health().stale:
                bus.send(_frame(*protocol.encode(STATUS, counter)))
                counter = (counter + 1) % 16
                await asyncio.sleep(0.02)
                while bus.recv(0) is not None:
                    pass
            while client.health().stale_since_s is None:
                await asyncio.sleep(0.001)
            stale_since_s, last_s = client.health().stale_since_s, monitor.last_accepted_s
            assert stale_since_s is not None and last_s is not None
            detection_ms.append((stale_since_s - last_s) * 1e3)
    finally:
        runner.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await runner
        bus.shutdown()
    return summarize("staleness: last valid status -> client reports stale", detection_ms, "ms")


def bench_codec() -> list[str]:
    command = MotionCommand(MotionPattern.COUNTER_STEER, 1.5, 0.2, -0.1)
    arbitration_id, data = protocol.encode(STATUS, 5)
    monitor = ReceiveMonitor(MonitorParams(0.02, 0.1))
    n = 20_000
    encode_us = timeit.timeit(lambda: protocol.encode(command, 3), number=n) / n * 1e6
    decode_us = (
        timeit.timeit(lambda: protocol.decode(arbitration_id, data, 0.0), number=n) / n * 1e6
    )
    frame_times_s = iter([i * 0.02 for i in range(n + 1)])

    def update() -> None:
        now_s = next(frame_times_s)
        monitor.update(now_s, round(now_s / 0.02) % 16)

    monitor_us = timeit.timeit(update, number=n) / n * 1e6
    return [
        f"codec: encode MotionCommand {encode_us:.1f} µs, decode PC104_Status {decode_us:.1f} µs, "
        f"ReceiveMonitor.update {monitor_us:.2f} µs per frame"
    ]


def main() -> None:
    print("PC104 link (benchmarks/bench_pc104.py)")
    for line in bench_codec():
        print(line)
    print(asyncio.run(bench_staleness()))
    for line in asyncio.run(bench_loaded_bus()):
        print(line)


if __name__ == "__main__":
    main()
