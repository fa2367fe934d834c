"""`dbw gnss ...`: what a technician uses when fitting a GNSS/INS receiver to the vehicle.

`probe` listens for a few seconds through the same client the daemon runs and says what it
heard (sentences and rates, fix, satellites, HDOP, sigma, heading, position, damaged lines)
and whether the autopilot could steer by it; `record` keeps every line as received, bad ones
included and marked, with its receive time, so a misbehaving receiver can be looked at later;
`twin` puts a simulated receiver on a pty to try both without hardware.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import math
import os
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import IO, Any

import click
import serial  # type: ignore[import-untyped]

from drivers.gnss.client import (
    BAUDRATES_BPS,
    DEFAULT_BAUDRATE_BPS,
    GnssClient,
    open_port,
    sentence_name,
)
from drivers.gnss.nmea import NmeaReceiver, Reject
from drivers.gnss.sentences import FixQuality, GgaFix, GstError, Heading, NmeaEvent

EXIT_NO_NMEA = 1
EXIT_USAGE = 2  # as appliance.cli.common's (not imported: it loads the whole `dbw` group)
# A position below this rate is too old between fixes for a 50 Hz tracker at 10 mph.
MIN_POSITION_RATE_HZ = 5.0
MAX_SIGMA_M = 0.10  # the paper's tracking tolerance is about a foot; sigma must be well inside
MAX_BAD_LINE_FRACTION = 0.05
NOT_A_MEASUREMENT = {FixQuality.INVALID, FixQuality.MANUAL, FixQuality.SIMULATION}
LONGEST_RECORDED_LINE_BYTES = 4096  # an unterminated run longer than this is cut and marked
RECORD_FORMAT = (
    "<monotonic_s> <utc_iso> <status> <line>: status is ok or why the line gave nothing "
    "(checksum, no_start, too_long, ignored_type, ...; partial: cut by the end or an unplug); "
    "the line as received, without its CR/LF, bytes outside printable ASCII as \\xNN"
)


def _baudrate(ctx: click.Context, param: click.Parameter, value: int) -> int:
    if value not in BAUDRATES_BPS:
        raise click.BadParameter(f"{value} is not one of {', '.join(map(str, BAUDRATES_BPS))}")
    return value


BAUD = click.option(
    "--baud",
    "baudrate_bps",
    type=int,
    default=DEFAULT_BAUDRATE_BPS,
    show_default=True,
    callback=_baudrate,
    help="Serial baud rate (8N1), as configured on the receiver.",
)


@click.group()
def gnss() -> None:
    """Probe and record a GNSS/INS receiver (NMEA 0183 on a serial port)."""


def _open_or_exit(port: str, baudrate_bps: int) -> None:
    """Fail fast, with the system's reason and no traceback, when the port cannot be opened."""
    try:
        open_port(port, baudrate_bps).close()
    except (serial.SerialException, OSError) as exc:
        click.echo(f"error: cannot open {port}: {exc}", err=True)
        sys.exit(EXIT_NO_NMEA)


async def _run_for(coroutine: Any, seconds: float | None) -> None:
    """Until ``seconds`` have passed (None: until Ctrl-C); the coroutine is cancelled then."""
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(coroutine, seconds)


@dataclass
class ProbeStats:
    """What the probe heard, event by event."""

    counts: Counter[str] = field(default_factory=Counter)
    first_s: dict[str, float] = field(default_factory=dict)
    last_s: dict[str, float] = field(default_factory=dict)
    qualities: Counter[str] = field(default_factory=Counter)
    gga: GgaFix | None = None
    gst: GstError | None = None
    heading: Heading | None = None
    valid_headings: int = 0

    def add(self, event: NmeaEvent, stamp_s: float) -> None:
        name = sentence_name(event)
        self.counts[name] += 1
        self.first_s.setdefault(name, stamp_s)
        self.last_s[name] = stamp_s
        if isinstance(event, GgaFix):
            self.gga = event
            self.qualities[_quality_name(event.quality)] += 1
        elif isinstance(event, GstError):
            self.gst = event
        elif isinstance(event, Heading):
            self.heading = event
            self.valid_headings += event.valid

    def rate_hz(self, name: str, seconds: float) -> float:
        """From the first to the last arrival; the listening time when there was one."""
        n = self.counts[name]
        span_s = self.last_s.get(name, 0.0) - self.first_s.get(name, 0.0)
        return (n - 1) / span_s if n >= 2 and span_s > 0 else n / seconds

    def sigma_m(self) -> float | None:
        gst = self.gst
        if gst is None or gst.sigma_lat_m is None or gst.sigma_lon_m is None:
            return None
        return max(gst.sigma_lat_m, gst.sigma_lon_m)


def _quality_name(quality: FixQuality | None) -> str:
    return "none" if quality is None else f"{quality.name.lower().replace('_', ' ')} ({quality})"


def verdict(
    stats: ProbeStats,
    bad_lines: int,
    seconds: float,
    min_rate_hz: float = MIN_POSITION_RATE_HZ,
    max_sigma_m: float = MAX_SIGMA_M,
) -> list[str]:
    """Why the autopilot could not steer by this receiver as heard; empty: it could."""
    reasons = []
    gga = stats.gga
    if gga is None:
        reasons.append("no GGA: no position")
    else:
        rate = stats.rate_hz("GGA", seconds)
        if rate < min_rate_hz:
            reasons.append(f"position at {rate:.1f} Hz, below {min_rate_hz:g} Hz")
        if gga.quality is None or gga.quality in NOT_A_MEASUREMENT:
            reasons.append(f"fix quality {_quality_name(gga.quality)}")
    sigma = stats.sigma_m()
    if sigma is None:
        reasons.append("no sigma (GST): the position error is unknown")
    elif sigma > max_sigma_m:
        reasons.append(f"sigma {sigma:.3f} m above {max_sigma_m:g} m")
    if stats.valid_headings == 0:
        reasons.append("no valid true heading (HDT or THS)")
    lines = sum(stats.counts.values()) + bad_lines
    if lines and bad_lines / lines > MAX_BAD_LINE_FRACTION:
        reasons.append(f"{bad_lines / lines:.0%} of lines damaged (cable, noise or baud rate)")
    return reasons


def _report(stats: ProbeStats, client: GnssClient, seconds: float) -> list[str]:
    health = client.health()
    rates = ", ".join(
        f"{name} {stats.rate_hz(name, seconds):.1f} Hz ({n})"
        for name, n in sorted(stats.counts.items())
    )
    lines = [
        f"{client.port} at {client.baudrate_bps} baud, {seconds:g} s, {health.bytes_received} bytes"
    ]
    lines.append(f"sentences: {rates or 'none'}")
    gga = stats.gga
    if gga is not None:
        seen = ", ".join(f"{q} x{n}" for q, n in stats.qualities.items())
        lines.append(f"fix: {_quality_name(gga.quality)}; seen: {seen}")
        lines.append(f"satellites: {gga.satellites}, HDOP: {gga.hdop}")
        if gga.lat_deg is not None and gga.lon_deg is not None:
            lines.append(
                f"position: {abs(gga.lat_deg):.8f} {'N' if gga.lat_deg >= 0 else 'S'}, "
                f"{abs(gga.lon_deg):.8f} {'E' if gga.lon_deg >= 0 else 'W'}, "
                f"altitude {gga.altitude_m} m"
            )
    sigma = stats.sigma_m()
    lines.append("sigma (GST): " + ("absent" if sigma is None else f"{sigma:.3f} m"))
    heading = stats.heading
    if heading is None:
        lines.append("heading: absent (no HDT or THS)")
    else:
        value = (
            "empty" if heading.heading_rad is None else f"{math.degrees(heading.heading_rad):.2f}°"
        )
        lines.append(
            f"heading: present ({heading.sentence}, {value}, valid in "
            f"{stats.valid_headings} of {stats.counts[heading.sentence]})"
        )
    rejects = ", ".join(f"{reason} {n}" for reason, n in sorted(health.rejects.items()))
    lines.append(f"rejected lines: {rejects or 'none'}")
    if health.last_bad_line:
        lines.append(f"last bad line ({health.last_bad_reason}): {health.last_bad_line}")
    if health.reconnects or health.last_error:
        lines.append(f"link: {health.reconnects} reconnects; last error: {health.last_error}")
    return lines


@gnss.command()
@click.argument("port")
@BAUD
@click.option(
    "--seconds",
    type=click.FloatRange(min=0.0, min_open=True),
    default=5.0,
    show_default=True,
    help="How long to listen.",
)
@click.option(
    "--max-sigma-m",
    type=click.FloatRange(min=0.0),
    default=MAX_SIGMA_M,
    show_default=True,
    help="The largest GST sigma (either horizontal axis) the verdict accepts.",
)
def probe(port: str, baudrate_bps: int, seconds: float, max_sigma_m: float) -> None:
    """Listen on PORT and say what the receiver sends and whether the autopilot could use it.

    Usable means: GGA at 5 Hz or more with a real fix, GST with sigma at most --max-sigma-m,
    a valid true heading (HDT or THS), and at most 5 % damaged lines. Exit status 0 when any
    NMEA was heard, 1 when none was or the port cannot be opened.
    """
    _open_or_exit(port, baudrate_bps)
    stats = ProbeStats()
    client = GnssClient(port, stats.add, baudrate_bps=baudrate_bps, max_age_s=math.inf)
    asyncio.run(_run_for(client.run(lambda: None), seconds))
    health = client.health()
    for line in _report(stats, client, seconds):
        click.echo(line)
    if health.events_ok == 0 and not health.rejects.get(Reject.IGNORED_TYPE):
        hint = "nothing received" if health.bytes_received == 0 else "wrong baud rate?"
        click.echo(f"verdict: no NMEA sentence heard in {seconds:g} s ({hint})")
        sys.exit(EXIT_NO_NMEA)
    reasons = verdict(stats, health.error_count, seconds, max_sigma_m=max_sigma_m)
    if reasons:
        click.echo("verdict: NOT usable for autopilot: " + "; ".join(reasons))
    else:
        click.echo("verdict: usable for autopilot")


class LineLog:
    """Raw chunks in, one log line per received line out, marked ok or with its reject reason.

    Lines are split as `NmeaReceiver` splits them (at CR or LF, empty ones skipped) and each is
    judged by a receiver of its own, so the mark is what the daemon would have made of it.
    """

    def __init__(self, out: IO[str], wall: Callable[[], dt.datetime]) -> None:
        self._out = out
        self._wall = wall
        self._buf = bytearray()
        self._judge = NmeaReceiver()
        self.statuses: Counter[str] = Counter()

    def feed(self, data: bytes, now_s: float) -> None:
        self._buf += data
        while True:
            ends = [i for i in (self._buf.find(b"\r"), self._buf.find(b"\n")) if i >= 0]
            if not ends:
                break
            line = bytes(self._buf[: min(ends)])
            del self._buf[: min(ends) + 1]
            if line:
                self._write(now_s, self._status(line), line)
        if len(self._buf) > LONGEST_RECORDED_LINE_BYTES:
            self._write(now_s, Reject.TOO_LONG, bytes(self._buf))
            self._buf.clear()

    def link(self, up: bool, reason: str, now_s: float) -> None:
        if not up:
            self.finish(now_s)
        text = "link up" if up else f"link down: {reason}"
        self._out.write(f"# {now_s:.6f} {self._wall().isoformat()} {text}\n")

    def finish(self, now_s: float) -> None:
        """What is left without a line end (the recording stopped, the cable went)."""
        if self._buf:
            self._write(now_s, "partial", bytes(self._buf))
            self._buf.clear()

    def _status(self, line: bytes) -> str:
        before = self._judge.counts
        self._judge.receive_data(line + b"\n")
        if any(True for _ in self._judge.events()):
            return "ok"
        new = self._judge.counts - before
        return next(iter(new), "unknown")

    def _write(self, now_s: float, status: str, line: bytes) -> None:
        self.statuses[status] += 1
        text = line.decode("latin-1").encode("unicode_escape").decode("ascii")
        self._out.write(f"{now_s:.6f} {self._wall().isoformat()} {status} {text}\n")


@gnss.command()
@click.argument("port")
@click.option("--output", "-o", metavar="FILE", type=click.Path(dir_okay=False), required=True)
@BAUD
@click.option(
    "--seconds",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Stop after this long. Default: until Ctrl-C.",
)
def record(port: str, output: str, baudrate_bps: int, seconds: float | None) -> None:
    """Write every line PORT sends to FILE, as received, with its receive time.

    One line per received line: <monotonic_s> <utc_iso> <status> <line>. status is ok, or
    why the line gave nothing (checksum, no_start, too_long, ignored_type, ...), or partial
    (cut by the end of the recording or an unplug). The line is as received, without its
    CR/LF, bytes outside printable ASCII written as \\xNN. Lines starting with # are comments
    (the header; link up/down). Ctrl-C ends it cleanly with a summary.
    """
    _open_or_exit(port, baudrate_bps)
    started_s = time.monotonic()
    try:
        out = open(output, "w", encoding="utf-8", newline="\n")  # noqa: SIM115  # closed below
    except OSError as exc:
        click.echo(f"error: cannot write {output}: {exc.strerror or exc}", err=True)
        sys.exit(EXIT_USAGE)
    with out:
        wall = _utc_now
        log = LineLog(out, wall)
        out.write(
            f"# dbw gnss record: port={port} baud={baudrate_bps} started={wall().isoformat()}\n"
        )
        out.write(f"# format: {RECORD_FORMAT}\n")
        client = GnssClient(
            port,
            lambda event, stamp_s: None,
            baudrate_bps=baudrate_bps,
            max_age_s=math.inf,
            tap=log.feed,
            on_link=log.link,
        )
        interrupted = False
        try:
            asyncio.run(_run_for(client.run(lambda: None), seconds))
        except KeyboardInterrupt:
            interrupted = True
        log.finish(time.monotonic())
    elapsed_s = time.monotonic() - started_s
    total = sum(log.statuses.values())
    bad = ", ".join(f"{s} {n}" for s, n in sorted(log.statuses.items()) if s != "ok")
    click.echo(
        f"{'interrupted: ' if interrupted else ''}{total} lines in {elapsed_s:.1f} s to {output} "
        f"({log.statuses['ok']} ok{'; ' + bad if bad else ''}; {client.reconnects} reconnects)"
    )


def _utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


@gnss.command()
@click.option("--pty-dir", type=click.Path(file_okay=False, exists=True), required=True)
@click.option("--seconds", type=click.FloatRange(min=0.0, min_open=True), default=None)
@click.option("--speed-mps", type=float, default=2.0, show_default=True)
@click.option("--radius-m", type=click.FloatRange(min=1.0), default=20.0, show_default=True)
@click.option("--jump-m", type=click.FloatRange(min=0.0), default=0.0, show_default=True)
@click.option("--corrupt-fraction", type=click.FloatRange(0.0, 1.0), default=0.0)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
def twin(
    pty_dir: str,
    seconds: float | None,
    speed_mps: float,
    radius_m: float,
    jump_m: float,
    corrupt_fraction: float,
    seed: int,
) -> None:
    """A simulated receiver on a pty at PTY_DIR/gnss, driving a circle, until Ctrl-C."""
    from appliance.sim.twins.gnss import GnssTwin, GnssTwinParams

    params = GnssTwinParams(jump_m=jump_m, corrupt_fraction=corrupt_fraction)
    receiver = GnssTwin(os.path.join(pty_dir, "gnss"), params, seed=seed)
    start_s = time.monotonic()

    def pose(now_s: float) -> tuple[float, float, float, float]:
        angle = speed_mps * (now_s - start_s) / radius_m
        east, north = radius_m * math.cos(angle), radius_m * math.sin(angle)
        return east, north, angle + math.pi / 2, speed_mps

    click.echo(f"NMEA on {receiver.port_path}", err=True)
    try:
        asyncio.run(_run_for(receiver.run(pose), seconds))
    except KeyboardInterrupt:
        pass
    finally:
        receiver.close()
