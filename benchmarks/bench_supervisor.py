"""Supervisor overhead: heartbeat cost, hang detection, restart time, watchdog withholding.

Figures (issue 2): the restart time of a crashed service, and the time from a hung
critical service to the last systemd WATCHDOG ping.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import tempfile
import time
import timeit
from pathlib import Path

from appliance.config import load_config
from appliance.daemon import Daemon
from appliance.supervisor import ServiceContext, ServiceSpec, ServiceState, Supervisor
from benchmarks.stats import summarize
from safety.watchdog import RestartPolicy
from tools.fake_notify import FakeNotifySocket

BACKOFF_S = 0.1  # the default restart_initial_backoff_s


def bench_beat_cost() -> str:
    sup = Supervisor(
        [
            ServiceSpec(
                "x", run=_forever, critical=True, restart=RestartPolicy(), heartbeat_deadline_s=1.0
            )
        ]
    )
    ctx = ServiceContext(sup.records["x"], time.monotonic)
    n = 200_000
    seconds = timeit.timeit(ctx.beat, number=n)
    return f"heartbeat cost: {seconds / n * 1e6:.3f} µs per beat"


async def _forever(ctx: ServiceContext) -> None:
    while True:
        ctx.beat()
        await asyncio.sleep(0.005)


async def bench_restart_and_detection(trials: int = 20) -> list[str]:
    crash_at: list[float] = []
    up_at: list[float] = []
    hang_at: list[float] = []
    lateness_ms: list[float] = []
    mode = {"crash": True}

    async def service(ctx: ServiceContext) -> None:
        ctx.beat()
        up_at.append(time.monotonic())
        await asyncio.sleep(0.05)
        if mode["crash"]:
            crash_at.append(time.monotonic())
            raise RuntimeError("benchmark crash")
        hang_at.append(time.monotonic())
        await asyncio.Event().wait()

    policy = RestartPolicy(
        initial_backoff_s=BACKOFF_S, backoff_factor=1.0, backoff_cap_s=BACKOFF_S, max_restarts=10**6
    )
    sup = Supervisor(
        [ServiceSpec("svc", service, critical=True, restart=policy, heartbeat_deadline_s=0.1)]
    )
    record = sup.records["svc"]
    task = asyncio.create_task(sup.run())
    try:
        while len(crash_at) < trials:
            await asyncio.sleep(0.01)
        mode["crash"] = False
        start = len(hang_at)
        while len(hang_at) < start + trials:
            seen = len(hang_at)
            while record.state is not ServiceState.HUNG:
                await asyncio.sleep(0.0005)
            last_beat_s = record.heartbeat.last_beat_s
            assert last_beat_s is not None
            lateness_ms.append((time.monotonic() - (last_beat_s + 0.1)) * 1e3)
            while len(hang_at) == seen:
                await asyncio.sleep(0.005)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    restart_s = [up - crash for crash, up in zip(crash_at, up_at[1:], strict=False)][:trials]
    overhead_ms = [(r - BACKOFF_S) * 1e3 for r in restart_s]
    return [
        summarize(
            f"restart time, crash -> first beat again (backoff {BACKOFF_S} s)",
            [r * 1e3 for r in restart_s],
            "ms",
        ),
        summarize("restart overhead beyond the backoff", overhead_ms, "ms"),
        summarize(
            "hang detection, heartbeat deadline (0.1 s) -> HUNG, lateness", lateness_ms, "ms"
        ),
    ]


async def bench_watchdog_withholding(trials: int = 8) -> list[str]:
    """Hang a critical service that also ignores cancellation; watch the pings stop."""
    watchdog_s = 2.0  # as in systemd/dbw.service
    config = load_config("sim")
    directory = Path(tempfile.mkdtemp(prefix="dbw-b", dir="/tmp"))
    last_ping_after_hang_ms: list[float] = []
    withheld_after_hang_ms: list[float] = []
    systemd_fires_after_hang_s: list[float] = []
    try:
        for _ in range(trials):
            with FakeNotifySocket(directory) as notify:
                os.environ.update(notify.environment(watchdog_s))
                hang = asyncio.Event()
                release = asyncio.Event()
                hung_at: list[float] = []

                async def control_like(
                    ctx: ServiceContext,
                    hang: asyncio.Event = hang,
                    release: asyncio.Event = release,
                    hung_at: list[float] = hung_at,
                ) -> None:
                    while not hang.is_set():
                        ctx.beat()
                        await asyncio.sleep(0.02)
                    hung_at.append(time.monotonic())
                    while not release.is_set():
                        with contextlib.suppress(asyncio.CancelledError):
                            await asyncio.sleep(0.01)

                spec = ServiceSpec(
                    "planner",
                    control_like,
                    critical=True,
                    restart=RestartPolicy(),
                    heartbeat_deadline_s=config.supervision.control_heartbeat_deadline_s,
                )
                daemon = Daemon(config, extra_services=[spec])
                run = asyncio.ensure_future(daemon.run(handle_signals=False))
                await asyncio.to_thread(notify.wait_for, "WATCHDOG=1")
                # hang at a random phase of the ping cycle
                await asyncio.sleep(0.1 + (time.monotonic() * 7.3) % 1.0)
                hang.set()
                while daemon.supervisor.critical_healthy():
                    await asyncio.sleep(0.0005)
                withheld = time.monotonic()
                # pings come every WatchdogSec/2: one more period proves they stopped
                await asyncio.sleep(watchdog_s / 2 + 0.2)
                pings = notify.lines("WATCHDOG=1")
                t_hang = hung_at[0]
                last_ping_after_hang_ms.append((pings[-1].at_s - t_hang) * 1e3)
                withheld_after_hang_ms.append((withheld - t_hang) * 1e3)
                systemd_fires_after_hang_s.append(pings[-1].at_s + watchdog_s - t_hang)
                daemon.request_stop("benchmark")
                await run
                release.set()
                await asyncio.sleep(0.05)
    finally:
        for key in ("NOTIFY_SOCKET", "WATCHDOG_USEC"):
            os.environ.pop(key, None)
        shutil.rmtree(directory, ignore_errors=True)
    return [
        summarize("hang -> watchdog pings withheld", withheld_after_hang_ms, "ms"),
        summarize(
            "hang -> last WATCHDOG=1 (negative: last ping came before the hang)",
            last_ping_after_hang_ms,
            "ms",
        ),
        summarize(
            f"hang -> systemd would kill (last ping + WatchdogSec={watchdog_s:g}s)",
            systemd_fires_after_hang_s,
            "s",
        ),
    ]


def main() -> None:
    from appliance.logs import configure_logging

    configure_logging("critical", stream=open(os.devnull, "w"), json=True)  # noqa: SIM115
    print("## supervisor")
    print(bench_beat_cost())
    for line in asyncio.run(bench_restart_and_detection()):
        print(line)
    for line in asyncio.run(bench_watchdog_withholding()):
        print(line)


if __name__ == "__main__":
    main()
