"""How late this machine wakes a sleeper at a deadline, by the way it sleeps.

The floor under every jitter figure of the control loop: a loop that does nothing but
wake at 50 Hz, five ways. ``epoll`` with a timeout is how asyncio sleeps (whole
milliseconds, rounded up, so up to 1 ms late before the machine adds its own latency);
a timerfd armed at the deadline is how the control loop's ticker sleeps now
(appliance/timerfd.py); ``time.sleep`` is the kernel's own precision. The last two are
asyncio loops: one timing its wake-ups with ``call_later``, one with the daemon's
``FixedRateTicker``. Figures are printed, never asserted.

    python -m benchmarks.bench_wakeup [--wakeups 1500] [--rate-hz 50]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import select
import sys
import time
from collections.abc import Callable

from appliance.timerfd import open_timerfd
from appliance.timing import FixedRateTicker
from benchmarks.stats import summarize


def lateness_ms(period_s: float, wakeups: int, wait: Callable[[float], None]) -> list[float]:
    late = []
    deadline_s = time.monotonic() + period_s
    for _ in range(wakeups):
        wait(deadline_s)
        late.append((time.monotonic() - deadline_s) * 1e3)
        deadline_s += period_s
    return late


def sleeping(deadline_s: float) -> None:
    time.sleep(max(deadline_s - time.monotonic(), 0.0))


def epoll_waiter() -> Callable[[float], None]:
    poller = select.epoll()

    def wait(deadline_s: float) -> None:
        poller.poll(max(deadline_s - time.monotonic(), 0.0))

    return wait


def timerfd_waiter() -> Callable[[float], None] | None:
    timerfd = open_timerfd()
    if timerfd is None:
        return None
    poller = select.epoll()
    poller.register(timerfd.fileno(), select.EPOLLIN)

    def wait(deadline_s: float) -> None:
        timerfd.arm(deadline_s)
        poller.poll(max(deadline_s - time.monotonic(), 0.0) + 1.0)
        timerfd.clear()

    return wait


async def asyncio_call_later(period_s: float, wakeups: int) -> list[float]:
    late = []
    deadline_s = time.monotonic() + period_s
    for _ in range(wakeups):
        await asyncio.sleep(max(deadline_s - time.monotonic(), 0.0))
        late.append((time.monotonic() - deadline_s) * 1e3)
        deadline_s += period_s
    return late


async def asyncio_ticker(period_s: float, wakeups: int) -> tuple[list[float], bool]:
    ticker = FixedRateTicker(period_s)
    ticker.stats = type(ticker.stats)(window=wakeups + 1)
    await ticker.tick()  # the first tick is due at once: not a wake-up
    for _ in range(wakeups):
        await ticker.tick()
    precise = ticker.precise
    values = ticker.stats._jitter_s.values()[1:] * 1e3
    ticker.close()
    return [float(v) for v in values], precise


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_wakeup")
    parser.add_argument("--wakeups", type=int, default=1500)
    parser.add_argument("--rate-hz", type=float, default=50.0)
    args = parser.parse_args(argv or [])  # `make bench` calls main() with its own argv
    period_s = 1.0 / args.rate_hz
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print("## wake-up lateness at a deadline (benchmarks/bench_wakeup.py)")
    print(f"machine: {platform.platform()}, Python {platform.python_version()}, load {load}")
    print(f"{args.wakeups} wake-ups at {args.rate_hz:g} Hz each; lateness after the deadline")
    n = args.wakeups
    print(summarize("time.sleep", lateness_ms(period_s, n, sleeping), "ms"))
    print(summarize("epoll with a timeout", lateness_ms(period_s, n, epoll_waiter()), "ms"))
    waiter = timerfd_waiter()
    if waiter is None:
        print("epoll on a timerfd: no timerfd on this system")
    else:
        print(summarize("epoll on a timerfd", lateness_ms(period_s, n, waiter), "ms"))
    print(summarize("asyncio call_later", asyncio.run(asyncio_call_later(period_s, n)), "ms"))
    late, precise = asyncio.run(asyncio_ticker(period_s, n))
    how = "timerfd" if precise else "the loop's timer: no timerfd here"
    print(summarize(f"asyncio FixedRateTicker ({how})", late, "ms"))


if __name__ == "__main__":
    main(sys.argv[1:])
