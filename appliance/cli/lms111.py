"""`dbw lms111 ...`: what a person uses when mounting a scanner on the vehicle.

`probe` reads identity, configuration and status without changing anything; `record`
stores the raw telegram stream (so a misbehaving device can be replayed byte for byte);
`decode` replays a recording through the same protocol core the daemon uses, and with
``--export`` writes its scans out beam by beam (JSON lines or CSV) for other tools.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import dataclasses
import json
import os
import sys
from typing import TYPE_CHECKING, TextIO

import click

from drivers.lms111 import Dialect

if TYPE_CHECKING:
    from drivers.lms111.scan import Scan

EXIT_DEVICE_ERROR = 1
EXIT_USAGE = 2


def _endpoint(value: str) -> tuple[str, int]:
    host, sep, port = value.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise click.BadParameter(f"expected HOST:PORT, e.g. 192.168.0.11:2111 (got {value!r})")
    return host, int(port)


DIALECT = click.option(
    "--dialect",
    type=click.Choice(["cola-a", "cola-b"]),
    default="cola-a",
    show_default=True,
    help="CoLa-A (ASCII) or CoLa-B (binary), as configured on the scanner.",
)


def _dialect(name: str) -> Dialect:
    return Dialect.COLA_A if name == "cola-a" else Dialect.COLA_B


@click.group()
def lms111() -> None:
    """Probe, record and decode a SICK LMS111."""


@lms111.command()
@click.argument("endpoint", metavar="HOST:PORT")
@click.option("--timeout-s", type=click.FloatRange(min=0.1), default=2.0, show_default=True)
@DIALECT
def probe(endpoint: str, timeout_s: float, dialect: str) -> None:
    """Log in and print the scanner's identity, configuration and status (JSON)."""
    from drivers.lms111.handshake import probe as run_probe
    from drivers.lms111.session import Lms111Error

    host, port = _endpoint(endpoint)
    try:
        result = asyncio.run(run_probe(host, port, timeout_s, _dialect(dialect)))
    except (Lms111Error, OSError) as exc:
        click.echo(f"{host}:{port}: {exc}", err=True)
        sys.exit(EXIT_DEVICE_ERROR)
    click.echo(json.dumps(result.to_dict(), indent=2, default=str))


@lms111.command()
@click.argument("endpoint", metavar="HOST:PORT")
@click.argument("file", type=click.Path(dir_okay=False, writable=True))
@click.option("--seconds", type=click.FloatRange(min=0.0, min_open=True), required=True)
@click.option("--frequency-hz", type=click.Choice(["25", "50"]), default="50", show_default=True)
@click.option(
    "--resolution-deg", type=click.Choice(["0.25", "0.5"]), default="0.5", show_default=True
)
@DIALECT
def record(
    endpoint: str,
    file: str,
    seconds: float,
    frequency_hz: str,
    resolution_deg: str,
    dialect: str,
) -> None:
    """Configure the scanner, subscribe, and store the raw stream in FILE."""
    from drivers.lms111.recording import record as run_record
    from drivers.lms111.session import Lms111Error

    host, port = _endpoint(endpoint)
    if frequency_hz == "50" and resolution_deg == "0.25":
        raise click.BadParameter("the LMS111 cannot scan at 50 Hz with 0.25 deg resolution")
    try:
        stats = asyncio.run(
            run_record(
                host,
                port,
                file,
                seconds,
                _dialect(dialect),
                scan_frequency_hz=float(frequency_hz),
                angular_resolution_deg=float(resolution_deg),
            )
        )
    except (Lms111Error, OSError) as exc:
        click.echo(f"{host}:{port}: {exc}", err=True)
        sys.exit(EXIT_DEVICE_ERROR)
    click.echo(json.dumps(dataclasses.asdict(stats), indent=2))


@lms111.command()
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="One JSON object per scan.")
@click.option(
    "--export",
    "export_format",
    type=click.Choice(["jsonl", "csv"]),
    default=None,
    help="Write every scan beam by beam instead of one line per scan: JSON lines (one "
    "object per scan, with arrays) or CSV (one row per beam, with a header).",
)
@click.option(
    "--out",
    "out_file",
    metavar="PATH",
    type=click.Path(dir_okay=False),
    default=None,
    help="Where --export writes. Default: stdout (the report then goes to stderr).",
)
def decode(file: str, as_json: bool, export_format: str | None, out_file: str | None) -> None:
    """Replay FILE through the protocol core and print every scan and dropped telegram.

    With --export, the scans themselves are written instead: per scan its receive time,
    device time and counters, and per beam the device angle in degrees (90° straight out
    of the window), the sensor-frame angle in radians (device − 90°, what perception
    takes), the range in metres (0 = no echo) and the intensity (RSSI digits). The dropped
    telegrams and the summary still follow, on stdout with --out, on stderr without.
    """
    from drivers.lms111.recording import (
        RecordingError,
        ReplayError,
        read_header,
        scan_line,
        scan_summary,
        summarize_recording,
    )

    if out_file is not None and export_format is None:
        raise click.UsageError("--out names where --export writes: give --export jsonl|csv")
    report_to_stderr = export_format is not None and out_file is None
    export = None
    if export_format is not None:
        try:  # before --out is created: a file that is no recording leaves nothing behind
            read_header(file)
        except RecordingError as exc:
            click.echo(f"{file}: {exc}", err=True)
            sys.exit(EXIT_USAGE)
        export = _exporter(export_format, out_file, file)

    def show(event: object) -> None:
        if isinstance(event, ReplayError):
            text = (
                json.dumps({"error": event.message, "receive_time_s": event.receive_time_s})
                if as_json
                else f"t={event.receive_time_s:.3f} dropped telegram: {event.message}"
            )
        elif export is not None:
            export(event)  # type: ignore[arg-type]
            return
        else:
            text = json.dumps(scan_summary(event)) if as_json else scan_line(event)  # type: ignore[arg-type]
        click.echo(text, err=report_to_stderr)

    try:
        with contextlib.ExitStack() as stack:
            if export is not None:
                stack.callback(export.close)
            summary = summarize_recording(file, on_event=show)
    except RecordingError as exc:
        click.echo(f"{file}: {exc}", err=True)
        sys.exit(EXIT_USAGE)
    except BrokenPipeError:  # `... --export csv | head`: the reader has had enough
        _quiet_stdout()
        sys.exit(0)
    except OSError as exc:
        click.echo(f"{exc.filename or file}: {exc.strerror or exc}", err=True)
        sys.exit(EXIT_USAGE)
    text = json.dumps(summary.to_dict()) if as_json else _summary_text(summary.to_dict())
    click.echo(text, err=report_to_stderr)
    if summary.truncated:
        click.echo(f"{file}: {summary.truncated}", err=True)
        sys.exit(EXIT_DEVICE_ERROR)


class _Exporter:
    """Writes each scan as it is replayed: a JSON line, or one CSV row per beam."""

    def __init__(self, export_format: str, stream: TextIO, owned: bool) -> None:
        self._format = export_format
        self._stream = stream
        self._owned = owned
        self._index = 0
        self._csv = csv.writer(stream, lineterminator="\n")
        if export_format == "csv":
            from drivers.lms111.recording import EXPORT_CSV_COLUMNS

            self._csv.writerow(EXPORT_CSV_COLUMNS)

    def __call__(self, scan: Scan) -> None:
        from drivers.lms111.recording import scan_export, scan_export_rows

        if self._format == "csv":
            self._csv.writerows(scan_export_rows(scan, self._index))
        else:
            self._stream.write(json.dumps(scan_export(scan, self._index)) + "\n")
        self._index += 1

    def close(self) -> None:
        if self._owned:
            self._stream.close()
        else:
            self._stream.flush()


def _exporter(export_format: str, out_file: str | None, file: str) -> _Exporter:
    if out_file is None:
        return _Exporter(export_format, sys.stdout, owned=False)
    if os.path.abspath(out_file) == os.path.abspath(file):
        click.echo(f"{out_file}: --out would overwrite the recording being read", err=True)
        sys.exit(EXIT_USAGE)
    try:
        stream = open(out_file, "w", encoding="utf-8", newline="")  # noqa: SIM115  # closed by close()
    except OSError as exc:
        click.echo(f"{out_file}: cannot write the export: {exc.strerror or exc}", err=True)
        sys.exit(EXIT_USAGE)
    return _Exporter(export_format, stream, owned=True)


def _quiet_stdout() -> None:
    """After a broken pipe, point stdout at /dev/null so the interpreter's final flush
    does not complain a second time."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def _summary_text(summary: dict[str, object]) -> str:
    return (
        f"{summary['scans']} scans, {summary['errors']} dropped telegrams, "
        f"{summary['dropped_scans']} scan counter gaps over {summary['duration_s']:.3f} s "
        f"({summary['dialect']})"
    )
