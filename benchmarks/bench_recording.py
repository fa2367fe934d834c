"""What the flight recorder costs the daemon, how much it writes, and how fast replay runs.

The daemon runs as `dbw run --config sim` builds it (bench_soak's harness: the simulated
vehicle in its own process, both scanners streaming at the profile's rate, the boards and
the PC104 link), engaged in speed hold, first with the recorder off and then on (the same
length each). Per run: control-loop wake-up jitter (p50, p99, max), missed cycles, the
core's step p99, and the CPU of the daemon, the simulated vehicle and the recorder's
process. For the recorded run: bytes per minute on disk, messages sent and dropped (in
the daemon, for a full pipe; in the recorder, for a low disk), and `dbw record check`'s
verdict. Then replay of that recording (both scanners' samples in it), each way three
times, its real-time factor best and median: from messages already in memory (the core,
the codec and the comparison), from the files (reading and checking them too), and
`dbw replay --compare` in a process of its own; and whether every output matched. The
daemon runs at the systemd unit's niceness, replay at the niceness the benchmark was
started with (``nice -n 19`` on a shared machine).

    python -m benchmarks.bench_recording                 # 60 s off, 60 s on
    python -m benchmarks.bench_recording --seconds 20
    python -m benchmarks.bench_recording --seconds 20 --keep /tmp/rec   # keep the files
    python -m benchmarks.bench_recording --replay /tmp/rec              # replay them only

Figures are printed, never asserted. The goal (issue 13): jitter p99 with the recorder
within 0.5 ms of without it; 0 messages lost at nominal load; replay >= 50x real time.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from appliance.logs import configure_logging
from appliance.modes import Mode
from appliance.recording.reader import RecordingReader, read_metadata
from appliance.recording.replay import Replayer, ReplayResult, core_from_metadata
from benchmarks.bench_soak import Soak, run_as_the_unit_does, say

REPEATS = 3  # each replay figure: the best and the median of this many


async def one_run(seconds: float, record_dir: str | None, speed_mps: float) -> list[str]:
    with tempfile.TemporaryDirectory(prefix="dbw-rec-bench-", dir="/tmp") as directory:
        bench = Soak(50.0, os.path.join(directory, "control.sock"), record_dir=record_dir)
        run = asyncio.ensure_future(bench.daemon.run(handle_signals=False))
        try:
            await bench.until("READY", lambda: bench.core.state.mode is Mode.READY)
            await asyncio.sleep(2.0)
            await bench.speed_hold(speed_mps)
            title = "recorder ON" if record_dir else "recorder off"
            lines = await bench.phase(f"{title}, engaged, speed hold {speed_mps:g} m/s", seconds)
            recorder = bench.daemon.recorder
            if recorder is not None:
                status = recorder.status()
                lines.append(
                    f"    recorder: sent {status.get('sent')}, dropped in the daemon "
                    f"{status.get('dropped_in_daemon') or 0}, dropped by the recorder "
                    f"{status.get('dropped') or 0}, state {status.get('state')}"
                )
        finally:
            bench.daemon.request_stop("benchmark over")
            await asyncio.wait_for(run, 10.0)
    return lines


def verdict(reader: RecordingReader) -> str:
    report = reader.report
    return "complete" if report.finished and not report.problems else f"{report.problems}"


def recording_lines(directory: Path, seconds: float | None) -> list[str]:
    files = sorted(directory.glob("*.mcap"))
    total = sum(p.stat().st_size for p in files)
    readers = [RecordingReader(p) for p in files]
    messages = []
    for reader in readers:
        messages.extend(reader.read_all())
    span_s = max(r.report.duration_s for r in readers) if readers else 0.0
    measured = f"{seconds:g} s measured" if seconds is not None else "an earlier run"
    lines = [
        f"  recording: {len(files)} file(s), {total / 1e6:.2f} MB over {span_s:.1f} s "
        f"= {total / 1e6 / span_s * 60:.1f} MB per minute (whole run: start-up, engage, "
        f"{measured})"
        if span_s
        else "  recording: empty",
        "  check: " + "; ".join(f"{r.path.name} {verdict(r)}" for r in readers),
    ]
    if not readers:
        return lines
    metadata = readers[0].report.metadata

    def in_memory() -> ReplayResult:
        return Replayer(core_from_metadata(metadata)).feed(messages)

    def from_files() -> ReplayResult:
        replayer = Replayer(core_from_metadata(read_metadata(files[0])))
        for path in files:
            replayer.feed_file(path)
        return replayer.result

    result, times = timed(in_memory)
    lines.append(
        f"  replay in memory (messages already read): {result.cycles} cycles, "
        f"{result.duration_s:.1f} s recorded, {factors(result.duration_s, times)}; "
        f"divergent cycles {result.divergent_cycles}"
    )
    result, times = timed(from_files)
    lines.append(
        f"  replay from the files (read, checked, decoded, stepped, compared): "
        f"{factors(result.duration_s, times)}; divergent cycles {result.divergent_cycles}"
    )
    lines.append(cli_line(files[-1]))
    return lines


def timed(run: Callable[[], ReplayResult]) -> tuple[ReplayResult, list[float]]:
    """``run`` REPEATS times: its last result and each run's wall time."""
    times = []
    for _ in range(REPEATS):
        started = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - started)
    return result, times


def factors(recorded_s: float, times: list[float]) -> str:
    best, median = min(times), statistics.median(times)
    return (
        f"best {recorded_s / best:.1f}x, median {recorded_s / median:.1f}x real time "
        f"(of {len(times)}: {', '.join(f'{t:.2f}' for t in times)} s)"
    )


def cli_line(path: Path) -> str:
    """`dbw replay FILE --compare` as a person runs it: a new process, imports and all."""
    times, reported = [], []
    for _ in range(REPEATS):
        started = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-m", "appliance", "replay", str(path), "--compare", "--json"],
            capture_output=True,
            text=True,
            check=False,
        )
        times.append(time.perf_counter() - started)
        if done.returncode != 0:
            return f"  dbw replay --compare: exit {done.returncode}: {done.stderr.strip()[-300:]}"
        summary = json.loads(done.stdout)
        reported.append(summary["real_time_factor"])
        recorded_s = summary["recorded_s"]
    return (
        f"  dbw replay --compare (own process): {factors(recorded_s, times)} end to end; "
        f"its own figure (from its first message) best {max(reported)}x, median "
        f"{statistics.median(reported)}x; divergent cycles {summary['divergent_cycles']}"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_recording")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--speed-mps", type=float, default=1.0)
    parser.add_argument(
        "--keep", type=Path, default=None, help="Record into this directory and keep it."
    )
    parser.add_argument(
        "--replay",
        type=Path,
        default=None,
        help="Record nothing: only replay the recording in this directory (from --keep).",
    )
    args = parser.parse_args(argv if argv is not None else sys.argv[1:])
    configure_logging("warning", stream=sys.stderr, json=True)
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    started_nice = os.getpriority(os.PRIO_PROCESS, 0)
    niceness = run_as_the_unit_does() if args.replay is None else "none (replay only)"
    say(
        "## the flight recorder's cost, size and replay (benchmarks/bench_recording.py)",
        f"machine: {platform.platform()}, Python {platform.python_version()}, "
        f"os.cpu_count() = {os.cpu_count()}, load average = {load}; daemon: {niceness}",
    )
    if args.replay is not None:
        say(*recording_lines(args.replay, None))
        return
    say(*asyncio.run(one_run(args.seconds, None, args.speed_mps)))
    with contextlib.ExitStack() as stack:
        if args.keep is None:
            directory = Path(
                stack.enter_context(
                    tempfile.TemporaryDirectory(prefix="dbw-recordings-", dir="/tmp")
                )
            )
        else:
            directory = args.keep
            directory.mkdir(parents=True, exist_ok=True)
        say(*asyncio.run(one_run(args.seconds, str(directory), args.speed_mps)))
        # Replay is a command a person runs: at the niceness this was started with.
        os.setpriority(os.PRIO_PROCESS, 0, started_nice)
        say(f"  replay at nice {started_nice}, as this benchmark was started")
        say(*recording_lines(directory, args.seconds))


if __name__ == "__main__":
    main()
