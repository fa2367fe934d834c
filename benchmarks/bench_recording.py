"""What the flight recorder costs the daemon, how much it writes, and how fast replay runs.

The daemon runs as `dbw run --config sim` builds it (bench_soak's harness: the simulated
vehicle in its own process, both scanners streaming at the profile's rate, the boards and
the PC104 link), engaged in speed hold, first with the recorder off and then on (the same
length each). Per run: control-loop wake-up jitter (p50, p99, max), missed cycles, the
core's step p99, and the CPU of the daemon, the simulated vehicle and the recorder's
process. For the recorded run: bytes per minute on disk, messages sent and dropped (in
the daemon, for a full pipe; in the recorder, for a low disk), and `dbw record check`'s
verdict. Then replay of that recording (both scanners' samples in it): its real-time
factor and whether every output matched.

    python -m benchmarks.bench_recording                 # 60 s off, 60 s on
    python -m benchmarks.bench_recording --seconds 20

Figures are printed, never asserted. The goal (issue 13): jitter p99 with the recorder
within 0.5 ms of without it; 0 messages lost at nominal load; replay >= 50x real time.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from appliance.logs import configure_logging
from appliance.modes import Mode
from appliance.recording.reader import RecordingReader
from appliance.recording.replay import Replayer, core_from_metadata
from benchmarks.bench_soak import Soak, run_as_the_unit_does, say


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


def recording_lines(directory: Path, seconds: float) -> list[str]:
    files = sorted(directory.glob("*.mcap"))
    total = sum(p.stat().st_size for p in files)
    readers = [RecordingReader(p) for p in files]
    messages = []
    for reader in readers:
        messages.extend(reader.read_all())
    span_s = max(r.report.duration_s for r in readers) if readers else 0.0
    lines = [
        f"  recording: {len(files)} file(s), {total / 1e6:.2f} MB over {span_s:.1f} s "
        f"= {total / 1e6 / span_s * 60:.1f} MB per minute (whole run: start-up, engage, "
        f"{seconds:g} s measured)"
        if span_s
        else "  recording: empty",
        "  check: " + "; ".join(f"{r.path.name} {verdict(r)}" for r in readers),
    ]
    if not readers:
        return lines
    core = core_from_metadata(readers[0].report.metadata)
    replayer = Replayer(core)
    started = time.perf_counter()
    replayer.feed(messages)
    elapsed = time.perf_counter() - started
    result = replayer.result
    lines.append(
        f"  replay: {result.cycles} cycles, {result.duration_s:.1f} s recorded, in "
        f"{elapsed:.2f} s = {result.duration_s / elapsed:.0f}x real time (messages already "
        f"read; reading and CRC-checking the files took the rest); divergent cycles "
        f"{result.divergent_cycles}"
    )
    started = time.perf_counter()
    replayer = Replayer(core_from_metadata(readers[0].report.metadata))
    for path in files:
        replayer.feed(RecordingReader(path).messages())
    elapsed = time.perf_counter() - started
    lines.append(
        f"  replay from the files (read, checked, decoded, stepped, compared): "
        f"{elapsed:.2f} s = {result.duration_s / elapsed:.0f}x real time"
    )
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_recording")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--speed-mps", type=float, default=1.0)
    args = parser.parse_args(argv if argv is not None else sys.argv[1:])
    configure_logging("warning", stream=sys.stderr, json=True)
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    niceness = run_as_the_unit_does()
    say(
        "## the flight recorder's cost, size and replay (benchmarks/bench_recording.py)",
        f"machine: {platform.platform()}, Python {platform.python_version()}, "
        f"os.cpu_count() = {os.cpu_count()}, load average = {load}; daemon: {niceness}",
    )
    say(*asyncio.run(one_run(args.seconds, None, args.speed_mps)))
    with tempfile.TemporaryDirectory(prefix="dbw-recordings-", dir="/tmp") as directory:
        say(*asyncio.run(one_run(args.seconds, directory, args.speed_mps)))
        say(*recording_lines(Path(directory), args.seconds))


if __name__ == "__main__":
    main()
