"""`dbw lms111 ...`: what a person uses when mounting a scanner on the vehicle.

`probe` reads identity, configuration and status without changing anything; `record`
stores the raw telegram stream (so a misbehaving device can be replayed byte for byte);
`decode` replays a recording through the same protocol core the daemon uses.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import sys

import click

from drivers.lms111 import Dialect

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
def decode(file: str, as_json: bool) -> None:
    """Replay FILE through the protocol core and print every scan and dropped telegram."""
    from drivers.lms111.recording import (
        RecordingError,
        ReplayError,
        scan_line,
        scan_summary,
        summarize_recording,
    )

    def show(event: object) -> None:
        if isinstance(event, ReplayError):
            text = (
                json.dumps({"error": event.message, "receive_time_s": event.receive_time_s})
                if as_json
                else f"t={event.receive_time_s:.3f} dropped telegram: {event.message}"
            )
        else:
            text = json.dumps(scan_summary(event)) if as_json else scan_line(event)  # type: ignore[arg-type]
        click.echo(text)

    try:
        summary = summarize_recording(file, on_event=show)
    except RecordingError as exc:
        click.echo(f"{file}: {exc}", err=True)
        sys.exit(EXIT_USAGE)
    click.echo(json.dumps(summary.to_dict()) if as_json else _summary_text(summary.to_dict()))
    if summary.truncated:
        click.echo(f"{file}: {summary.truncated}", err=True)
        sys.exit(EXIT_DEVICE_ERROR)


def _summary_text(summary: dict[str, object]) -> str:
    return (
        f"{summary['scans']} scans, {summary['errors']} dropped telegrams, "
        f"{summary['dropped_scans']} scan counter gaps over {summary['duration_s']:.3f} s "
        f"({summary['dialect']})"
    )
