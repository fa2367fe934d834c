"""`dbw record check` and `dbw replay`: what a recording holds, and the core run on it again.

Exit status: 0 when all is well (a whole file; a replay that matched), 1 when something
needs a look (a file cut short but readable up to its last whole chunk; a replay that
diverged), 2 for input that cannot be used at all (no such file, not a recording).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import click

from appliance.cli.common import CONFIG_OPTION, bad_input, load_or_exit


@click.group()
def record() -> None:
    """Recordings the daemon writes (MCAP; README, Recording and replay)."""


@record.command("list")
@CONFIG_OPTION
def list_recordings(config_name: str | None) -> None:
    """The recordings in the vehicle's recording directory, oldest first."""
    from appliance.recording.service import recording_directory

    config = load_or_exit(config_name)
    directory = recording_directory(config)
    files = sorted(directory.glob("*.mcap")) if directory.is_dir() else []
    if not files:
        click.echo(f"no recordings in {directory}")
        return
    total = 0
    for path in files:
        size = path.stat().st_size
        total += size
        companion = path.with_suffix(".can.log")
        extra = f" + {companion.stat().st_size / 1e6:.1f} MB candump" if companion.exists() else ""
        click.echo(f"{path.name}  {size / 1e6:8.1f} MB{extra}")
    click.echo(f"{len(files)} files, {total / 1e6:.1f} MB in {directory}")


@record.command("check")
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="One JSON object per file.")
def check(files: tuple[Path, ...], as_json: bool) -> None:
    """Read each FILE front to back, check every chunk's CRC, say what is there."""
    from appliance.recording.reader import RecordingReader

    worst = 0
    for path in files:
        reader = RecordingReader(path)
        for _ in reader.messages():
            pass
        report = reader.report
        if report.messages == 0 and report.problems:
            status = 2
        elif report.problems or not report.finished:
            status = 1
        else:
            status = 0
        worst = max(worst, status)
        if as_json:
            click.echo(
                json.dumps(
                    {
                        "path": str(path),
                        "finished": report.finished,
                        "truncated": report.truncated,
                        "chunks": report.chunks,
                        "bad_chunks": report.bad_chunks,
                        "messages": report.messages,
                        "duration_s": round(report.duration_s, 3),
                        "per_topic": report.per_topic,
                        "session": report.session,
                        "problems": report.problems,
                    }
                )
            )
            continue
        state = (
            "complete"
            if report.finished and not report.problems
            else ("unreadable" if status == 2 else "cut short: readable up to its last whole chunk")
        )
        click.echo(f"{path}: {state}")
        click.echo(
            f"  {report.messages} messages in {report.chunks} chunks over "
            f"{report.duration_s:.1f} s"
            + (f", {report.bad_chunks} damaged chunks skipped" if report.bad_chunks else "")
        )
        meta = report.metadata.get("dbw", {})
        if meta:
            click.echo(
                f"  vehicle {meta.get('vehicle', '?')}, dbw {meta.get('version', '?')}, "
                f"started {meta.get('started_utc', '?')}, session {meta.get('session', '?')[:12]}"
            )
        for topic, count in sorted(report.per_topic.items()):
            click.echo(f"  {topic:<34} {count:>8}")
        for problem in report.problems:
            click.echo(f"  problem: {problem}")
    sys.exit(worst)


@click.command()
@click.argument("file", type=click.Path(path_type=Path))
@click.option(
    "--compare",
    is_flag=True,
    help="List the first divergences (time, field, recorded vs replayed); exit 1 on any.",
)
@click.option(
    "--tolerance",
    "tolerances",
    multiple=True,
    metavar="FIELD=ABS",
    help="Accept a difference up to ABS in fields matching FIELD (a pattern over dotted "
    "paths such as 'output.pc104_pose.*'); repeatable. Default: exact.",
)
@click.option(
    "--until",
    "until_s",
    type=click.FloatRange(min=0.0),
    default=None,
    help="Stop at this time (seconds from the recording's start).",
)
@click.option("--dump", is_flag=True, help="With --until: print the core's inputs then.")
@click.option("--json", "as_json", is_flag=True, help="The summary as JSON.")
def replay(
    file: Path,
    compare: bool,
    tolerances: tuple[str, ...],
    until_s: float | None,
    dump: bool,
    as_json: bool,
) -> None:
    """Run the recorded inputs of FILE through the core again and compare the outputs.

    The earlier files of the same recording session in FILE's directory are replayed
    first (the core's state starts where the daemon started it); the vehicle file and the
    calibration are the recorded ones.
    """
    from appliance.recording.reader import RecordingReader, session_files
    from appliance.recording.replay import (
        Replayer,
        ReplayError,
        Tolerance,
        core_from_metadata,
    )

    if dump and until_s is None:
        bad_input("--dump needs --until T")
    if not file.is_file():
        bad_input(f"no such recording: {file}")
    try:
        parsed = [Tolerance.parse(t) for t in tolerances]
    except ValueError as exc:
        bad_input(str(exc))
    files = session_files(file)
    first = RecordingReader(files[0])
    metadata = first.read_metadata()
    if not metadata and first.report.problems:
        bad_input(f"{files[0]}: not a recording ({'; '.join(first.report.problems)})")
    try:
        core = core_from_metadata(metadata)
    except ReplayError as exc:
        bad_input(f"{files[0]}: {exc}")
    dumped: dict[str, Any] = {}

    class Stop(Exception):
        pass

    def on_cycle(log_ns: int, now_s: float, inputs: Any, output: Any) -> None:
        start_ns = replayer.result.first_log_time_ns or log_ns  # the file's first message
        if until_s is not None and (log_ns - start_ns) / 1e9 >= until_s:
            if dump:
                dumped.update(_dump(log_ns - start_ns, now_s, inputs, output))
            raise Stop

    replayer = Replayer(core, parsed, on_cycle=on_cycle)
    readers: list[RecordingReader] = []
    started = time.perf_counter()
    try:
        for path in files:
            readers.append(RecordingReader(path))  # kept: its report, should replay stop in it
            replayer.feed_file(readers[-1])
    except Stop:
        pass
    except ReplayError as exc:
        click.echo(f"error: replay stopped: {exc}", err=True)
        sys.exit(1)
    elapsed_s = time.perf_counter() - started
    if dumped:
        click.echo(json.dumps(dumped, indent=2))
        return
    result = replayer.result
    problems = [f"{r.path.name}: {p}" for r in readers for p in r.report.problems]
    if not any(r.report.messages for r in readers):
        bad_input(f"{files[0]}: no messages ({'; '.join(problems) or 'empty'})")
    start_ns = result.first_log_time_ns or 0
    summary = {
        "files": [str(p) for p in files],
        "cycles": result.cycles,
        "cycles_before_first_core_start": result.cycles_skipped,
        "requests": result.requests,
        "core_starts": result.resets,
        "recorded_s": round(result.duration_s, 3),
        "replay_s": round(elapsed_s, 3),
        "real_time_factor": round(result.duration_s / elapsed_s, 1) if elapsed_s > 0 else None,
        "divergent_cycles": result.divergent_cycles,
        "divergences": [d.describe(start_ns) for d in result.divergences],
        "problems": problems,
    }
    if as_json:
        click.echo(json.dumps(summary))
    else:
        _print_summary(summary, compare)
    if result.cycles == 0:
        sys.exit(1)
    if compare and result.divergent_cycles:
        sys.exit(1)


def _print_summary(summary: dict[str, Any], compare: bool) -> None:
    click.echo(
        f"replayed {summary['cycles']} cycles ({summary['recorded_s']:.1f} s recorded, "
        f"{len(summary['files'])} file(s)) in {summary['replay_s']:.2f} s: "
        f"{summary['real_time_factor']}x real time"
    )
    if summary["cycles_before_first_core_start"]:
        click.echo(
            f"  {summary['cycles_before_first_core_start']} cycles before the first core "
            "start skipped (the recording began after the daemon did)"
        )
    if summary["divergent_cycles"] == 0:
        click.echo("  outputs match the recording exactly" if summary["cycles"] else "  nothing")
    else:
        click.echo(f"  {summary['divergent_cycles']} cycles diverged; first:")
        shown = summary["divergences"] if compare else summary["divergences"][:1]
        for line in shown:
            click.echo(f"    {line}")
    for problem in summary["problems"]:
        click.echo(f"  problem: {problem}")


def _dump(at_ns: int, now_s: float, inputs: Any, output: Any) -> dict[str, Any]:
    from appliance.core.inputs import ControlInputs
    from appliance.core.output import CoreOutput
    from appliance.recording.codec import encode

    encoded = encode(inputs, ControlInputs)
    encoded["scans"] = {
        side: None
        if scan is None
        else {
            "sensor": scan.sensor,
            "host_receive_time_s": scan.host_receive_time_s,
            "beams": len(scan.scan.ranges_m),
            "echoes": int(scan.valid.sum()),
        }
        for side, scan in inputs.scans.items()
    }
    return {
        "at_s": round(at_ns / 1e9, 6),
        "now_s": now_s,
        "inputs": encoded,
        "output": encode(output, CoreOutput),
    }
