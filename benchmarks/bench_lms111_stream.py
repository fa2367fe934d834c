"""Two LMS111 clients at 50 Hz against two twins: throughput, losses, CPU, reconnect time.

The twins run in a child process (spawned, with their own event loop), so this process's
CPU time is the drivers' alone: two clients reading, framing, decoding (541 beams + RSSI),
unwrapping device time and publishing 100 scans/s, as the daemon does. The child reports
its own CPU time too (the simulated scanners' cost: ray casting and encoding).

Figures:

* ``stream``: scans received per second per scanner (per-second counts), lost scans (scan
  counter gaps), reconnects (must stay 0: a false stall detection would show here), CPU %
  of one core for the clients' process and for the twins' process.
* ``reconnect``: a twin goes away (connections reset, port closed) for 0.5-3 s and comes
  back; the time from its return to the first scan received again, over ``--trials``
  outages, with the client's default backoff (0.1 s doubling to 1 s). Target: <= 2 s.

``python -m benchmarks.bench_lms111_stream --seconds 600`` gives the 10-minute figure.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import multiprocessing
import random
import time
from multiprocessing.connection import Connection
from typing import Any

from appliance.config.models import Lms111Endpoint, SensorMount
from appliance.logs import configure_logging
from benchmarks.stats import summarize
from drivers.lms111 import Dialect
from drivers.lms111.client import Lms111Client, Lms111Health
from drivers.lms111.mounted import MountedScan, mount_pose
from drivers.topics import Topic

MOUNTS = {
    "left": SensorMount(x_m=4.5, y_m=1.1, yaw_deg=45.0),
    "right": SensorMount(x_m=4.5, y_m=-1.1, yaw_deg=-45.0),
}


# ---- the child: two twins, controlled through a pipe --------------------------------------


def _twin_process(pipe: Connection, dialect: Dialect) -> None:
    asyncio.run(_serve_twins(pipe, dialect))


async def _serve_twins(pipe: Connection, dialect: Dialect) -> None:
    from appliance.sim import Pose2D, load_site
    from appliance.sim.twins.lms111 import Lms111Twin

    site = load_site("launcher")

    def approach(t_s: float) -> Pose2D:  # drive towards the launcher and back, 1 m/s
        x_m = -16.0 + abs((t_s % 16.0) - 8.0)
        return Pose2D(x_m, 0.3, math.radians(2.0))

    twins = {
        name: Lms111Twin(
            site,
            mount_pose(mount),
            approach,
            name=name,
            serial_number=0x01420001 + i,
            seed=i,
            range_bias_m=0.01 * (i + 1),
            dialect=dialect,
        )
        for i, (name, mount) in enumerate(MOUNTS.items())
    }
    for twin in twins.values():
        await twin.start()
    pipe.send({name: twin.port for name, twin in twins.items()})
    loop = asyncio.get_running_loop()
    cpu_start_s = time.process_time()
    wall_start_s = time.monotonic()
    while True:
        message: tuple[Any, ...] = await loop.run_in_executor(None, pipe.recv)
        if message[0] == "outage":
            _, name, down_s = message
            await twins[name].stop()
            await asyncio.sleep(down_s)
            await twins[name].start()
            pipe.send(("back", time.monotonic()))
        elif message[0] == "cpu_reset":
            cpu_start_s, wall_start_s = time.process_time(), time.monotonic()
            pipe.send(("ok",))
        elif message[0] == "cpu":
            used_s = time.process_time() - cpu_start_s
            pipe.send(("cpu", 100.0 * used_s / (time.monotonic() - wall_start_s)))
        else:
            break
    for twin in twins.values():
        await twin.stop()


# ---- the parent: two clients ------------------------------------------------------------


async def _ask(pipe: Connection, *message: Any) -> Any:
    pipe.send(message)
    return await asyncio.get_running_loop().run_in_executor(None, pipe.recv)


def _totals(health: Lms111Health) -> tuple[int, int, int, int]:
    return (health.scans_total, health.dropped_scans, health.reconnects, health.malformed_telegrams)


async def _stream(seconds: float, clients: dict[str, Lms111Client], pipe: Connection) -> None:
    await _ask(pipe, "cpu_reset")
    start = {name: _totals(c.health) for name, c in clients.items()}
    per_second: dict[str, list[float]] = {name: [] for name in clients}
    cpu_samples: list[float] = []
    wall_start_s, cpu_start_s = time.monotonic(), time.process_time()
    last = dict(start)
    last_wall_s, last_cpu_s = wall_start_s, cpu_start_s
    while (now_s := time.monotonic()) - wall_start_s < seconds:
        await asyncio.sleep(min(1.0, wall_start_s + seconds - now_s))
        wall_s, cpu_s = time.monotonic(), time.process_time()
        for name, client in clients.items():
            scans = client.health.scans_total
            per_second[name].append((scans - last[name][0]) / (wall_s - last_wall_s))
            last[name] = _totals(client.health)
        cpu_samples.append(100.0 * (cpu_s - last_cpu_s) / (wall_s - last_wall_s))
        last_wall_s, last_cpu_s = wall_s, cpu_s
    wall_s = time.monotonic() - wall_start_s
    clients_cpu = 100.0 * (time.process_time() - cpu_start_s) / wall_s
    (_, twins_cpu) = await _ask(pipe, "cpu")
    print(f"stream: two LMS111 clients at 50 Hz, 0.5°, RSSI on, {wall_s:.0f} s")
    for name, client in clients.items():
        scans, dropped, reconnects, malformed = (
            b - a for a, b in zip(start[name], _totals(client.health), strict=True)
        )
        print(
            summarize(f"  {name}: scans received per second", per_second[name], "scans/s")
            + f"; total {scans} ({scans / wall_s:.2f}/s), lost {dropped}, "
            f"reconnects {reconnects}, malformed {malformed}"
        )
    print(summarize("  clients' process CPU (per second)", cpu_samples, "% of a core"))
    print(f"  clients' process CPU, whole run: {clients_cpu:.1f} % of one core")
    print(f"  twins' process CPU (2 simulated scanners), whole run: {twins_cpu:.1f} % of one core")


async def _reconnect(
    trials: int, client: Lms111Client, topic: Topic[MountedScan], pipe: Connection
) -> None:
    rng = random.Random(1)
    latencies_s: list[float] = []
    for _ in range(trials):
        while client.health.state != "streaming":
            await asyncio.sleep(0.01)
        down_s = rng.uniform(0.5, 3.0)
        (_, back_s) = await _ask(pipe, "outage", "left", down_s)
        while True:
            sample = topic.latest()
            if sample is not None and sample.stamp_s >= back_s:
                latencies_s.append(sample.stamp_s - back_s)
                break
            await asyncio.sleep(0.002)
    print(f"reconnect: twin down 0.5-3 s, back on the same port, default backoff ({trials} trials)")
    print(summarize("  twin back -> first scan again", latencies_s, "s"))
    print("  target: <= 2 s (backoff cap 1 s + log-in and configuration)")


async def _run(seconds: float, trials: int, dialect: Dialect) -> None:
    context = multiprocessing.get_context("spawn")
    parent, child = context.Pipe()
    process = context.Process(target=_twin_process, args=(child, dialect), daemon=True)
    process.start()
    try:
        ports: dict[str, int] = await asyncio.get_running_loop().run_in_executor(None, parent.recv)
        topics = {name: Topic[MountedScan](f"scan.{name}") for name in MOUNTS}
        clients = {
            name: Lms111Client(
                name,
                Lms111Endpoint(host="127.0.0.1", port=ports[name]),
                MOUNTS[name],
                topics[name],
                dialect=dialect,
            )
            for name in MOUNTS
        }
        async with asyncio.TaskGroup() as group:
            tasks = [group.create_task(c.run(lambda: None)) for c in clients.values()]
            while any(c.health.state != "streaming" for c in clients.values()):
                await asyncio.sleep(0.01)
            await asyncio.sleep(1.0)  # warm-up
            await _stream(seconds, clients, parent)
            await _reconnect(trials, clients["left"], topics["left"], parent)
            for task in tasks:
                task.cancel()
    finally:
        parent.send(("quit",))
        process.join(timeout=5.0)
        if process.is_alive():
            process.kill()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seconds", type=float, default=60.0, help="streaming time (s)")
    parser.add_argument("--trials", type=int, default=10, help="reconnect trials")
    parser.add_argument("--dialect", choices=["cola-a", "cola-b"], default="cola-a")
    args = parser.parse_args([] if argv is None else argv)
    configure_logging("error", json=False)  # the outages are on purpose: no warnings
    dialect = Dialect.COLA_A if args.dialect == "cola-a" else Dialect.COLA_B
    print(f"dialect: {dialect.value}")
    asyncio.run(_run(args.seconds, args.trials, dialect))


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
