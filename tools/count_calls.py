"""Count the daemon's clock reads and event-loop lookups per second, by caller.

Why: on the vehicle's PC a ``time.monotonic()`` is a vDSO read and ``get_running_loop()``
a ``getpid()`` (Python 3.11) of a few hundred nanoseconds, but inside user-mode Linux,
where the HIL tests run, each is a trapped system call of about 30 us: there their number
per second is the daemon's CPU budget. strace does not see vDSO reads; this does.

    python tools/count_calls.py -- run --config sim --duration-s 20

runs ``dbw`` with those arguments in this process and prints, when it ends, the calls per
second and the callers that make most of them. Only this process is counted (with
``simulation.placement = "process"`` the simulated vehicle is another one).
"""

from __future__ import annotations

import argparse
import asyncio.events
import collections
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

_counts: collections.Counter[str] = collections.Counter()
_totals: collections.Counter[str] = collections.Counter()


def _counted(kind: str, original: Callable[[], Any]) -> Callable[[], Any]:
    def wrapper() -> Any:
        caller = sys._getframe(1).f_code
        _counts[f"{kind:<16} {caller.co_filename.rsplit('/', 1)[-1]}:{caller.co_name}"] += 1
        _totals[kind] += 1
        return original()

    return wrapper


def install() -> None:
    """Wrap the clocks and asyncio's loop lookups (before anything binds them by name)."""
    for name in ("monotonic", "perf_counter", "time"):
        setattr(time, name, _counted(f"time.{name}", getattr(time, name)))
    events = asyncio.events
    events.get_running_loop = _counted("get_running_loop", events.get_running_loop)
    events._get_running_loop = _counted("get_running_loop", events._get_running_loop)
    asyncio.get_running_loop = events.get_running_loop


def report(elapsed_s: float, top: int) -> list[str]:
    lines = [f"calls per second over {elapsed_s:.1f} s:"]
    lines += [f"  {kind:<18} {n / elapsed_s:8.0f}" for kind, n in sorted(_totals.items())]
    lines.append(f"the {top} callers that make most:")
    lines += [f"  {n / elapsed_s:8.0f}  {where}" for where, n in _counts.most_common(top)]
    return lines


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python tools/count_calls.py", description=__doc__)
    parser.add_argument("--top", type=int, default=20)
    parser.add_argument("dbw_args", nargs=argparse.REMAINDER, help="-- then dbw's arguments")
    args = parser.parse_args(argv)
    dbw_args = [a for a in args.dbw_args if a != "--"] or ["run", "--config", "sim"]
    original_perf_counter = time.perf_counter
    install()
    from appliance.cli import main as dbw_main

    started_s = original_perf_counter()
    code = 0
    sys.argv = ["dbw", *dbw_args]
    try:
        dbw_main()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 0
    print("\n".join(report(original_perf_counter() - started_s, args.top)), file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
