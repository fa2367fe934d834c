"""The recording's files: MCAP, split by size and time, under a quota, never filling the disk.

Why a set of files and not one: a vehicle records all day; one file would be too large
to copy off and a crash would cost its whole summary. Each file is a complete MCAP
(zstd chunks, message and chunk indexes, CRCs on) that opens alone in Foxglove, with the
vehicle file and calibration as metadata. A chunk is finished at least every
``flush_interval_ns``, so a file cut short by a crash or a power cut can be read up to
its last finished chunk (`dbw record check`).

The disk belongs to the vehicle before the recorder: below ``warn_free_bytes`` free the
recorder warns, below ``stop_free_bytes`` it stops writing (and counts what it drops),
and it resumes once the space is back above the warning level. The oldest closed files
are deleted while the directory holds more than the quota.

Time here is the messages' own log time (nanoseconds): the writer reads no clock, so it
is tested with made-up times; only the file names read the wall clock, through a
function the caller gives.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.writer import CompressionType, Writer

from appliance.logs import get_logger

log = get_logger("recording")

SUFFIX = ".mcap"
PROFILE = "dbw-applique"
# Free space is asked of the file system at most this often (log time).
DISK_CHECK_INTERVAL_NS = 1_000_000_000
# ... and after this many bytes, whatever the time: a burst cannot outrun the check.
DISK_CHECK_BYTES = 1 << 20
# After a write error (the directory gone, a read-only remount), wait this long to retry.
RETRY_INTERVAL_NS = 5_000_000_000
CHUNK_SIZE_BYTES = 1 << 20


@dataclass(frozen=True)
class ChannelSpec:
    """A channel and its schema, as MCAP wants them registered in every file."""

    topic: str
    schema_name: str
    schema_data: bytes  # a JSON Schema (encoding "jsonschema")
    message_encoding: str = "json"
    schema_encoding: str = "jsonschema"


@dataclass(frozen=True)
class FileSetParams:
    directory: Path
    split_size_bytes: int
    split_duration_ns: int
    quota_bytes: int
    warn_free_bytes: int
    stop_free_bytes: int
    flush_interval_ns: int
    prefix: str = "dbw"


@dataclass
class FileSetCounts:
    """What the file set did; dropped messages by reason."""

    messages: int = 0
    bytes_written: int = 0
    files_opened: int = 0
    files_deleted: int = 0
    dropped: dict[str, int] = field(default_factory=dict)

    def drop(self, reason: str, n: int = 1) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + n


def disk_free_bytes(path: Path) -> int:
    return shutil.disk_usage(path).free


class _OpenFile:
    """One MCAP file being written, with the channels registered in it so far."""

    def __init__(self, path: Path, opened_ns: int, metadata: dict[str, dict[str, str]]) -> None:
        self.path = path
        self.opened_ns = opened_ns
        self.last_flush_ns = opened_ns
        self.stream: BinaryIO = open(path, "xb")  # noqa: SIM115 - closed in close()
        self.writer = Writer(
            self.stream,
            chunk_size=CHUNK_SIZE_BYTES,
            compression=CompressionType.ZSTD,
            enable_crcs=True,
            enable_data_crcs=True,
        )
        self.writer.start(profile=PROFILE, library=f"{PROFILE} (mcap)")
        for name, data in metadata.items():
            self.writer.add_metadata(name, data)
        self.writer.flush()  # type: ignore[no-untyped-call]
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}

    def channel_id(self, spec: ChannelSpec) -> int:
        channel_id = self.channels.get(spec.topic)
        if channel_id is None:
            schema_id = self.schemas.get(spec.schema_name)
            if schema_id is None:
                schema_id = self.writer.register_schema(
                    spec.schema_name, spec.schema_encoding, spec.schema_data
                )
                self.schemas[spec.schema_name] = schema_id
            channel_id = self.writer.register_channel(spec.topic, spec.message_encoding, schema_id)
            self.channels[spec.topic] = channel_id
        return channel_id

    def size_bytes(self) -> int:
        return self.stream.tell()

    def close(self) -> None:
        try:
            self.writer.finish()  # type: ignore[no-untyped-call]
        finally:
            self.stream.close()


class RecordingFiles:
    """Writes messages to a set of MCAP files in one directory (see the module's why)."""

    def __init__(
        self,
        params: FileSetParams,
        metadata: dict[str, dict[str, str]],
        file_stamp: Callable[[], str],
        free_bytes: Callable[[Path], int] = disk_free_bytes,
    ) -> None:
        self.params = params
        self.metadata = metadata
        self._file_stamp = file_stamp
        self._free_bytes = free_bytes
        self.counts = FileSetCounts()
        self.state = "idle"  # idle | recording | stopped (disk) | failed (write error)
        self.reason = ""
        self._file: _OpenFile | None = None
        self._next_disk_check_ns: int | None = None
        self._bytes_since_check = 0
        self._retry_at_ns = 0
        self._warned = False

    @property
    def current_path(self) -> Path | None:
        return None if self._file is None else self._file.path

    def write(self, spec: ChannelSpec, log_time_ns: int, data: bytes, sequence: int) -> bool:
        """Write one message; False if it was dropped (and counted), never an exception."""
        if (
            self._next_disk_check_ns is None
            or log_time_ns >= self._next_disk_check_ns
            or self._bytes_since_check >= DISK_CHECK_BYTES
        ):
            self._check_disk(log_time_ns)
        if self.state == "stopped":
            self.counts.drop("disk_low")
            return False
        if self.state == "failed" and log_time_ns < self._retry_at_ns:
            self.counts.drop("write_error")
            return False
        try:
            file = self._file_for(log_time_ns)
            file.writer.add_message(
                file.channel_id(spec), log_time_ns, data, log_time_ns, sequence & 0xFFFFFFFF
            )
            if log_time_ns - file.last_flush_ns >= self.params.flush_interval_ns:
                file.writer.flush()  # type: ignore[no-untyped-call]
                file.last_flush_ns = log_time_ns
        except OSError as exc:
            self._fail(log_time_ns, exc)
            self.counts.drop("write_error")
            return False
        self.counts.messages += 1
        self.counts.bytes_written += len(data)
        self._bytes_since_check += len(data)
        return True

    def tick(self, log_time_ns: int) -> None:
        """Time passes without messages: flush what is buffered, check the disk."""
        if self._next_disk_check_ns is None or log_time_ns >= self._next_disk_check_ns:
            self._check_disk(log_time_ns)
        file = self._file
        if file is not None and log_time_ns - file.last_flush_ns >= self.params.flush_interval_ns:
            try:
                file.writer.flush()  # type: ignore[no-untyped-call]
                file.last_flush_ns = log_time_ns
            except OSError as exc:
                self._fail(log_time_ns, exc)

    def close(self) -> None:
        """Finish the open file (summary, indexes) so it reads fast and whole."""
        self._close_file()
        if self.state == "recording":
            self.state = "idle"

    # ---- files -------------------------------------------------------------------
    def _file_for(self, log_time_ns: int) -> _OpenFile:
        file = self._file
        if file is not None and (
            file.size_bytes() >= self.params.split_size_bytes
            or log_time_ns - file.opened_ns >= self.params.split_duration_ns
        ):
            self._close_file()
            file = None
        if file is None:
            file = self._open(log_time_ns)
        return file

    def _open(self, log_time_ns: int) -> _OpenFile:
        directory = self.params.directory
        directory.mkdir(parents=True, exist_ok=True)
        stamp = self._file_stamp()
        # The session's file count, never a gap's index: a name the quota freed is not
        # given again, so names sort in the order the files were written.
        for index in range(self.counts.files_opened, self.counts.files_opened + 1000):
            path = directory / f"{self.params.prefix}-{stamp}-{index:03d}{SUFFIX}"
            if not path.exists():
                break
        else:
            raise FileExistsError(f"no free file name for {stamp} in {directory}")
        file = _OpenFile(path, log_time_ns, self.metadata)
        self._file = file
        self.counts.files_opened += 1
        if self.state != "recording":
            self.state, self.reason = "recording", ""
        log.info("recording_file_opened", path=str(path))
        self._enforce_quota()
        return file

    def _close_file(self) -> None:
        file, self._file = self._file, None
        if file is None:
            return
        try:
            file.close()
            log.info("recording_file_closed", path=str(file.path), bytes=file.path.stat().st_size)
        except OSError as exc:
            log.error("recording_file_close_failed", path=str(file.path), error=str(exc))
        self._enforce_quota()

    def _enforce_quota(self) -> None:
        """Delete the oldest closed files while the directory is over its quota."""
        try:
            files = sorted(
                (p for p in self.params.directory.glob(f"*{SUFFIX}") if p.is_file()),
                key=lambda p: (p.stat().st_mtime_ns, p.name),
            )
            total = sum(p.stat().st_size for p in files)
        except OSError as exc:
            log.warning("recording_quota_unchecked", error=str(exc))
            return
        open_path = self.current_path
        for path in files:
            if total <= self.params.quota_bytes:
                break
            if path == open_path:
                continue
            try:
                size = path.stat().st_size
                path.unlink()
            except OSError as exc:
                log.warning("recording_quota_delete_failed", path=str(path), error=str(exc))
                continue
            total -= size
            self.counts.files_deleted += 1
            log.info("recording_file_deleted_for_quota", path=str(path), bytes=size)

    # ---- disk and errors ------------------------------------------------------------
    def _check_disk(self, log_time_ns: int) -> None:
        self._next_disk_check_ns = log_time_ns + DISK_CHECK_INTERVAL_NS
        self._bytes_since_check = 0
        directory = self.params.directory
        file = self._file
        if file is not None and not file.path.exists():
            # Deleted under us (or its directory): Linux takes writes to the unlinked
            # file without an error, so they would be lost without a word.
            self._fail(log_time_ns, FileNotFoundError(f"{file.path} was removed"))
        try:
            probe = directory if directory.exists() else _existing_parent(directory)
            free = self._free_bytes(probe)
        except OSError as exc:
            log.warning("recording_disk_unreadable", error=str(exc))
            return
        free_mb = round(free / 1e6, 1)
        if free < self.params.stop_free_bytes:
            if self.state != "stopped":
                self._close_file()
                self.state = "stopped"
                self.reason = f"disk low: {free_mb} MB free, stop below " + (
                    f"{self.params.stop_free_bytes / 1e6:.0f} MB"
                )
                log.error("recording_stopped_disk_low", free_mb=free_mb, path=str(directory))
            return
        if free < self.params.warn_free_bytes:
            if not self._warned:
                self._warned = True
                log.warning("recording_disk_low", free_mb=free_mb, path=str(directory))
            return
        self._warned = False
        if self.state == "stopped":
            self.state, self.reason = "idle", ""
            log.info("recording_resumed", free_mb=free_mb, path=str(directory))

    def _fail(self, log_time_ns: int, exc: OSError) -> None:
        log.error("recording_write_failed", error=str(exc), path=str(self.current_path))
        file, self._file = self._file, None
        if file is not None:
            with contextlib.suppress(OSError):
                file.stream.close()
        self.state, self.reason = "failed", f"write error: {exc}"
        self._retry_at_ns = log_time_ns + RETRY_INTERVAL_NS


def _existing_parent(path: Path) -> Path:
    for parent in path.parents:
        if parent.exists():
            return parent
    return Path(os.sep)
