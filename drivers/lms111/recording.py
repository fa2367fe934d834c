"""Recording an LMS111's raw TCP stream, and replaying it through the protocol core.

A recording keeps the bytes exactly as they came off the socket, chunk by chunk, each with
the host's monotonic receive time, and nothing decoded. Replaying feeds the same chunks to a
fresh `Lms111Connection`, so a recording of a misbehaving scanner reproduces its split
telegrams, garbage and broken checksums, and any later fix of the core can be checked
against it. The format (also in docs/protocols/lms111.md, "Recordings"):

* one header line: ``LMS111REC 1 `` + a JSON object + ``\\n``; the JSON holds at least
  ``host``, ``port``, ``dialect`` (``"CoLa-A"``/``"CoLa-B"``), ``started_monotonic_s``,
  ``started_utc`` (ISO 8601), plus what was asked of the scanner;
* then records until the end of the file, each: float64 receive time (monotonic seconds),
  uint32 length, then that many bytes (little-endian, ``struct`` format ``<dI``).

The stream begins at the TCP connect, so it includes the answers to the start-up requests;
the requests themselves (what the host sent) are not recorded. A file that ends inside a
record was cut off (a crash, a full disk): everything before it is replayed, then
`RecordingTruncated` says where.
"""

from __future__ import annotations

import datetime as dt
import json
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, Final

import numpy as np

from drivers.lms111.cola import ScanTelegram
from drivers.lms111.connection import Lms111Connection
from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import NEED_DATA, Dialect
from drivers.lms111.handshake import StreamSettings, start_streaming
from drivers.lms111.mounted import DEVICE_FORWARD_RAD
from drivers.lms111.scan import Scan
from drivers.lms111.session import Lms111Session

MAGIC: Final = b"LMS111REC"
VERSION: Final = 1
RECORD_HEADER: Final = struct.Struct("<dI")
MAX_CHUNK_BYTES: Final = 16 << 20  # a larger length means a corrupt file, not a big read
MAX_HEADER_BYTES: Final = 64 << 10


class RecordingError(ValueError):
    """Not a recording, or a damaged one."""


class RecordingTruncated(RecordingError):
    """The file ends inside a record (raised after every complete record was replayed)."""


@dataclass(frozen=True)
class RecordingHeader:
    version: int
    host: str
    port: int
    dialect: Dialect
    started_monotonic_s: float
    started_utc: str
    metadata: dict[str, Any]  # the whole JSON object, including the fields above


@dataclass(frozen=True)
class ReplayError:
    """A telegram the core dropped during replay, where it was and why."""

    receive_time_s: float
    offset: int  # byte offset of the record whose bytes completed the bad telegram
    message: str


@dataclass(frozen=True)
class RecordStats:
    path: str
    seconds: float
    chunks: int
    bytes: int
    scans: int
    malformed_telegrams: int
    first_scan_counter: int | None
    last_scan_counter: int | None


class RecordingWriter:
    """Header at open, then one record per `write_chunk`; a context manager."""

    def __init__(self, path: str | Path, metadata: dict[str, Any]) -> None:
        for key in ("host", "port", "dialect"):
            if key not in metadata:
                raise ValueError(f"recording metadata needs {key!r}")
        header = {
            "started_monotonic_s": time.monotonic(),
            "started_utc": dt.datetime.now(dt.UTC).isoformat(),
            **metadata,
        }
        self._file: BinaryIO = Path(path).open("wb")  # noqa: SIM115  # closed by close()
        self._file.write(MAGIC + b" %d " % VERSION + json.dumps(header).encode() + b"\n")
        self.chunks = 0
        self.bytes = 0

    def write_chunk(self, data: bytes, receive_time_s: float) -> None:
        self._file.write(RECORD_HEADER.pack(receive_time_s, len(data)))
        self._file.write(data)
        self.chunks += 1
        self.bytes += len(data)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()


def _read_header(file: BinaryIO, path: str | Path) -> RecordingHeader:
    line = file.readline(MAX_HEADER_BYTES)
    if not line.startswith(MAGIC + b" "):
        raise RecordingError(f"{path} is not an LMS111 recording (starts with {line[:16]!r})")
    if not line.endswith(b"\n"):
        raise RecordingTruncated(f"{path}: the header line is cut off")
    try:
        version_text, json_text = line[len(MAGIC) + 1 :].split(b" ", 1)
        version = int(version_text)
        metadata = json.loads(json_text)
        dialect = Dialect(metadata["dialect"])
        return RecordingHeader(
            version,
            str(metadata["host"]),
            int(metadata["port"]),
            dialect,
            float(metadata.get("started_monotonic_s", 0.0)),
            str(metadata.get("started_utc", "")),
            metadata,
        )
    except (ValueError, KeyError, TypeError) as exc:
        raise RecordingError(f"{path}: unreadable header: {exc}") from exc


def read_header(path: str | Path) -> RecordingHeader:
    with Path(path).open("rb") as file:
        return _read_header(file, path)


def iter_chunks(path: str | Path) -> Iterator[tuple[float, bytes, int]]:
    """(receive time, bytes, byte offset of the record) for every record, in order."""
    with Path(path).open("rb") as file:
        header = _read_header(file, path)
        if header.version != VERSION:
            raise RecordingError(f"{path}: recording version {header.version}, need {VERSION}")
        complete = 0
        while True:
            offset = file.tell()
            head = file.read(RECORD_HEADER.size)
            if not head:
                return
            if len(head) < RECORD_HEADER.size:
                raise RecordingTruncated(
                    f"{path}: truncated at byte {offset}: a record header needs "
                    f"{RECORD_HEADER.size} bytes, {len(head)} present "
                    f"(after {complete} complete records)"
                )
            receive_time_s, length = RECORD_HEADER.unpack(head)
            if length > MAX_CHUNK_BYTES:
                raise RecordingError(f"{path}: record at byte {offset} claims {length} bytes")
            data = file.read(length)
            if len(data) < length:
                raise RecordingTruncated(
                    f"{path}: truncated at byte {offset}: the record says {length} bytes, "
                    f"{len(data)} present (after {complete} complete records)"
                )
            complete += 1
            yield receive_time_s, data, offset


def iter_recording(path: str | Path) -> Iterator[Scan | ReplayError]:
    """Every scan (stamped with its recorded receive time) and every dropped telegram.

    Answers to the start-up requests are framed and skipped. Raises `RecordingTruncated`
    after the last complete record if the file was cut off, `RecordingError` if it is not
    a recording.
    """
    connection = Lms111Connection(read_header(path).dialect)
    for receive_time_s, data, offset in iter_chunks(path):
        connection.receive_data(data)
        while True:
            try:
                event = connection.next_event(host_receive_time_s=receive_time_s)
            except ProtocolError as exc:
                yield ReplayError(receive_time_s, offset, str(exc))
                continue
            if event is NEED_DATA:
                break
            if isinstance(event, ScanTelegram):
                yield event.scan


def _scan_identity(scan: Scan) -> dict[str, Any]:
    """When and from which device a scan came: the fields every JSON view of it starts with."""
    return {
        "host_receive_time_s": scan.host_receive_time_s,
        "serial_number": scan.serial_number,
        "scan_counter": scan.scan_counter,
        "telegram_counter": scan.telegram_counter,
        "device_time_us": scan.device_time_us,
        "transmit_time_us": scan.transmit_time_us,
        "device_status": scan.device_status,
        "scan_frequency_hz": scan.scan_frequency_hz,
    }


def scan_summary(scan: Scan) -> dict[str, Any]:
    """One scan as plain JSON-able values (``dbw lms111 decode --json``, one per line)."""
    ranges = scan.ranges_m
    valid = ranges[ranges > 0]
    intensities = scan.intensities
    angles = scan.angles_rad
    return {
        **_scan_identity(scan),
        "beams": len(ranges),
        "valid_beams": len(valid),
        "start_angle_deg": round(float(np.degrees(angles[0])), 4) if len(angles) else None,
        "angular_step_deg": round(float(np.degrees(scan.angular_step_rad)), 4),
        "channels": sorted(scan.channels),
        "min_range_m": round(float(valid.min()), 3) if len(valid) else None,
        "median_range_m": round(float(np.median(valid)), 3) if len(valid) else None,
        "max_range_m": round(float(valid.max()), 3) if len(valid) else None,
        "max_intensity": float(intensities.max()) if intensities is not None else None,
    }


def scan_line(scan: Scan) -> str:
    """One scan as one readable line (``dbw lms111 decode`` without ``--json``)."""
    s = scan_summary(scan)
    ranges = f"{s['min_range_m']}..{s['max_range_m']} m" if s["valid_beams"] else "no echo at all"
    return (
        f"t={s['host_receive_time_s']:.3f} scan #{s['scan_counter']} "
        f"telegram #{s['telegram_counter']} device {s['device_time_us']} µs "
        f"{s['scan_frequency_hz']:g} Hz {s['beams']} beams from {s['start_angle_deg']}° "
        f"step {s['angular_step_deg']}° ({s['valid_beams']} echoes, {ranges})"
    )


async def record(
    host: str,
    port: int,
    path: str | Path,
    seconds: float,
    dialect: Dialect = Dialect.COLA_A,
    *,
    scan_frequency_hz: float = 50.0,
    angular_resolution_deg: float = 0.5,
    timeout_s: float = 2.0,
    clock: Callable[[], float] = time.monotonic,
) -> RecordStats:
    """Log in, configure, subscribe, and write every chunk as received for ``seconds``.

    Raises `Lms111LinkError` / `Lms111ConfigError` like the client (what was received up
    to then stays in the file).
    """
    settings = StreamSettings(scan_frequency_hz, angular_resolution_deg)
    metadata = {
        "host": host,
        "port": port,
        "dialect": dialect.value,
        "scan_frequency_hz": scan_frequency_hz,
        "angular_resolution_deg": angular_resolution_deg,
        "seconds": seconds,
    }
    counters: list[int] = []
    with RecordingWriter(path, metadata) as writer:
        session = await Lms111Session.connect(
            host,
            port,
            dialect,
            connect_timeout_s=timeout_s,
            request_timeout_s=timeout_s,
            clock=clock,
            on_bytes=writer.write_chunk,
        )
        started_s = clock()
        try:
            await start_streaming(session, settings, ready_poll_s=0.5)
            counters.extend(scan.scan_counter for scan in session.queued_scans)
            while (remaining_s := started_s + seconds - clock()) > 0:
                try:
                    events = await session.read_events(remaining_s)
                except TimeoutError:
                    break
                counters.extend(e.scan.scan_counter for e in events if isinstance(e, ScanTelegram))
        finally:
            await session.close()
        return RecordStats(
            str(path),
            clock() - started_s,
            writer.chunks,
            writer.bytes,
            len(counters),
            session.connection.malformed_telegrams,
            counters[0] if counters else None,
            counters[-1] if counters else None,
        )


@dataclass(frozen=True)
class RecordingSummary:
    """What ``dbw lms111 decode FILE`` prints at the end."""

    path: str
    dialect: str
    scans: int
    errors: int
    dropped_scans: int  # scan counter gaps
    first_scan_counter: int | None
    last_scan_counter: int | None
    duration_s: float
    truncated: str | None  # the message, if the file was cut off

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def summarize_recording(
    path: str | Path, on_event: Callable[[Scan | ReplayError], None] | None = None
) -> RecordingSummary:
    """Replay a whole recording; ``on_event`` sees each scan and error on the way."""
    header = read_header(path)
    scans = errors = dropped = 0
    first: int | None = None
    last: int | None = None
    times: list[float] = []
    truncated: str | None = None
    try:
        for event in iter_recording(path):
            if on_event is not None:
                on_event(event)
            if isinstance(event, ReplayError):
                errors += 1
                continue
            if last is not None:
                gap = (event.scan_counter - last - 1) % 65536
                dropped += gap if gap < 32768 else 0
            first = event.scan_counter if first is None else first
            last = event.scan_counter
            scans += 1
            if event.host_receive_time_s is not None:
                times.append(event.host_receive_time_s)
    except RecordingTruncated as exc:
        truncated = str(exc)
    duration_s = times[-1] - times[0] if len(times) > 1 else 0.0
    return RecordingSummary(
        str(path), header.dialect.value, scans, errors, dropped, first, last, duration_s, truncated
    )


@dataclass(frozen=True)
class RecordedScans:
    """A whole recording's scans in memory (``dbw features``, ``dbw localize``)."""

    path: str
    header: RecordingHeader
    scans: tuple[Scan, ...]
    dropped_telegrams: int
    truncated: str | None  # the message, if the file was cut off: the scans before it are here


def read_scans(path: str | Path) -> RecordedScans:
    """Every scan of a recording, in order. A file cut off inside a record gives the scans
    before the cut and says where in ``truncated``; `RecordingError` if it is not a
    recording, `OSError` if it cannot be read."""
    header = read_header(path)
    scans: list[Scan] = []
    dropped = 0
    truncated: str | None = None
    try:
        for event in iter_recording(path):
            if isinstance(event, ReplayError):
                dropped += 1
            else:
                scans.append(event)
    except RecordingTruncated as exc:
        truncated = str(exc)
    return RecordedScans(str(path), header, tuple(scans), dropped, truncated)


# ``dbw lms111 decode --export csv``: one row per beam.
EXPORT_CSV_COLUMNS: Final = (
    "scan_index",
    "host_receive_time_s",
    "device_time_us",
    "scan_counter",
    "telegram_counter",
    "beam_index",
    "device_angle_deg",
    "sensor_angle_rad",
    "range_m",
    "intensity",
)


def _beams(scan: Scan) -> tuple[list[float], list[float], list[float], list[float] | None]:
    """Per beam: device angle (degrees, 90° out of the window), sensor-frame angle
    (radians, x out of the window, as perception takes it), range (m, 0 = no echo),
    intensity (RSSI1 digits, None when the scan carries none)."""
    ranges = scan.ranges_m
    beams = len(ranges)
    angles = scan.angles_rad[:beams]
    # The device counts in 1/10000 degree: four decimals give its number back exactly.
    device_deg = np.round(np.degrees(angles), 4)
    intensities = scan.intensities
    return (
        device_deg.tolist(),
        (angles - DEVICE_FORWARD_RAD).tolist(),
        ranges.tolist(),
        intensities[:beams].tolist() if intensities is not None else None,
    )


def scan_export(scan: Scan, index: int) -> dict[str, Any]:
    """One scan with every beam, as plain JSON-able values (``decode --export jsonl``).

    ``index`` is the scan's place in the recording (0 = the first). Angles are given
    twice: ``device_angle_deg`` as the LMS111 counts (90° straight out of the window) and
    ``sensor_angle_rad`` = device − 90° (x out of the window, counter-clockwise), what
    the perception code takes. ``range_m`` 0 means no echo.
    """
    device_deg, sensor_rad, ranges, intensities = _beams(scan)
    return {
        "scan_index": index,
        **_scan_identity(scan),
        "beams": len(ranges),
        "device_angle_deg": device_deg,
        "sensor_angle_rad": sensor_rad,
        "range_m": ranges,
        "intensity": intensities,
    }


def scan_export_rows(scan: Scan, index: int) -> Iterator[tuple[Any, ...]]:
    """One scan as CSV rows, one per beam, in `EXPORT_CSV_COLUMNS` order (an intensity the
    scan does not carry is an empty field)."""
    device_deg, sensor_rad, ranges, intensities = _beams(scan)
    time_s = scan.host_receive_time_s if scan.host_receive_time_s is not None else ""
    for beam, (deg, rad, range_m) in enumerate(zip(device_deg, sensor_rad, ranges, strict=True)):
        intensity = intensities[beam] if intensities is not None and beam < len(intensities) else ""
        yield (
            index,
            time_s,
            scan.device_time_us,
            scan.scan_counter,
            scan.telegram_counter,
            beam,
            deg,
            rad,
            range_m,
            intensity,
        )
