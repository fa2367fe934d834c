"""The recorder's own process: frames from the daemon in, MCAP files out.

Why a process: encoding JSON, compressing zstd chunks and writing files is steady work,
and a thread doing it would hold the interpreter lock the control loop needs when its
timer fires (a thread that runs Python keeps the lock up to the switch interval, 5 ms).
In a process of its own, niced below the daemon, it competes for a CPU only through the
scheduler, which hands the control loop's wake-up the CPU first. The daemon's side
(`appliance/recording/service.py`) only pickles what it records into a bounded pipe
buffer and drops, counting, what does not fit.

The frames on stdin are ``u32 length`` (little-endian) + a pickle from the parent: the
pickle is trusted because nothing but the daemon that started this process writes the
pipe. End of file (the daemon stopped, or died) finishes the open file properly and
ends the process. Once a second a status line (JSON) goes to stdout for ``dbw status``.
"""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import select
import signal
import struct
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from appliance.logs import configure_logging, get_logger
from appliance.recording.candump import CandumpLog
from appliance.recording.channels import (
    Encoded,
    encode_cycle,
    encode_raw,
    encode_recorder_counts,
    encode_request,
    encode_reset,
    encode_sample,
)
from appliance.recording.files import FileSetParams, RecordingFiles

log = get_logger("recording")

FRAME_HEADER = struct.Struct("<I")
MAX_FRAME_BYTES = 64 * 1024 * 1024
STATUS_INTERVAL_S = 1.0
READ_SIZE = 1 << 18
MAX_BAD_FRAMES_LOGGED = 20


class RecorderCore:
    """Turns the daemon's frames into MCAP messages; no pipes, so tests drive it directly."""

    def __init__(self, files: RecordingFiles) -> None:
        self.files = files
        self.candump = CandumpLog()
        self.sequence = 0
        self.frames = 0
        self.bad_frames = 0
        self.upstream_dropped: dict[str, int] = {}

    def handle(self, frame: tuple[Any, ...]) -> None:
        """One frame; one that cannot be encoded is counted and logged, never fatal (the
        rest of the recording is worth more than one message)."""
        self.frames += 1
        try:
            self._handle(frame)
        except Exception as exc:
            self.bad_frames += 1
            if self.bad_frames <= MAX_BAD_FRAMES_LOGGED:
                log.error(
                    "recording_frame_not_encoded",
                    kind=str(frame[0] if frame else "")[:40],
                    error=f"{type(exc).__name__}: {str(exc)[:200]}",
                )

    def _handle(self, frame: tuple[Any, ...]) -> None:
        kind = frame[0]
        if kind == "meta":
            self.files.metadata.update(frame[1])
            return
        log_ns = int(frame[1])
        messages: Any
        if kind == "sample":
            _, _, topic, seq, stamp_s, value = frame
            messages = encode_sample(topic, log_ns, seq, stamp_s, value)
        elif kind == "cycle":
            _, _, now_s, inputs, scan_seqs, output = frame
            messages = encode_cycle(log_ns, now_s, inputs, scan_seqs, output)
        elif kind == "request":
            _, _, now_s, request_kind, name, accepted, message = frame
            messages = encode_request(now_s, request_kind, name, accepted, message)
        elif kind == "raw":
            _, _, source, raw_kind, payload, t_s = frame
            messages = encode_raw(source, raw_kind, payload, t_s)
            self._write(log_ns, messages)
            if raw_kind == "can":
                self.candump.write(payload, log_ns, self.files.current_path)
            return
        elif kind == "reset":
            messages = encode_reset(frame[2])
        elif kind == "counts":
            self.upstream_dropped = dict(frame[2])
            messages = encode_recorder_counts(
                {"daemon_dropped": self.upstream_dropped, **self.status()}
            )
        else:
            self.bad_frames += 1
            log.error("recording_frame_unknown", kind=str(kind)[:40])
            return
        self._write(log_ns, messages)

    def _write(self, log_ns: int, messages: Any) -> None:
        encoded: Encoded
        for encoded in messages:
            self.sequence += 1
            self.files.write(encoded.spec, log_ns, encoded.data, self.sequence)

    def status(self) -> dict[str, Any]:
        counts = self.files.counts
        path = self.files.current_path
        return {
            "state": self.files.state,
            "reason": self.files.reason,
            "file": None if path is None else str(path),
            "messages": counts.messages,
            "bytes": counts.bytes_written,
            "files_opened": counts.files_opened,
            "files_deleted": counts.files_deleted,
            "dropped": dict(counts.dropped),
            "bad_frames": self.bad_frames,
        }


def file_stamp() -> str:
    return datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")


def params_from_json(text: str) -> tuple[FileSetParams, int]:
    raw = json.loads(text)
    params = FileSetParams(
        directory=Path(raw["directory"]),
        split_size_bytes=int(raw["split_size_bytes"]),
        split_duration_ns=int(raw["split_duration_ns"]),
        quota_bytes=int(raw["quota_bytes"]),
        warn_free_bytes=int(raw["warn_free_bytes"]),
        stop_free_bytes=int(raw["stop_free_bytes"]),
        flush_interval_ns=int(raw["flush_interval_ns"]),
    )
    return params, int(raw["clock_offset_ns"])


def serve(fd_in: int, status_out: Any, params: FileSetParams, clock_offset_ns: int) -> int:
    """Read frames from ``fd_in`` until end of file; 0 when it ended cleanly."""
    core = RecorderCore(RecordingFiles(params, {}, file_stamp))
    buffer = bytearray()
    next_status_s = time.monotonic()
    stopping = False

    def on_term(signum: int, _frame: Any) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon's Ctrl-C is the daemon's
    try:
        while not stopping:
            readable, _, _ = select.select([fd_in], [], [], 0.2)
            if readable:
                chunk = os.read(fd_in, READ_SIZE)
                if not chunk:
                    break
                buffer += chunk
                _drain(buffer, core)
            now_ns = time.monotonic_ns() + clock_offset_ns
            core.files.tick(now_ns)
            core.candump.flush()
            if time.monotonic() >= next_status_s:
                next_status_s = time.monotonic() + STATUS_INTERVAL_S
                _status_line(core, status_out)
    finally:
        core.files.close()
        core.candump.close()
        _status_line(core, status_out)
    return 0


def _status_line(core: RecorderCore, status_out: Any) -> None:
    """A daemon that is gone cannot read it: that is no reason to stop recording."""
    with contextlib.suppress(OSError, ValueError):
        print(json.dumps(core.status()), file=status_out, flush=True)


def _drain(buffer: bytearray, core: RecorderCore) -> None:
    while len(buffer) >= FRAME_HEADER.size:
        (length,) = FRAME_HEADER.unpack_from(buffer)
        if length > MAX_FRAME_BYTES:
            raise ValueError(f"frame of {length} bytes: the pipe is out of step")
        if len(buffer) < FRAME_HEADER.size + length:
            return
        payload = bytes(buffer[FRAME_HEADER.size : FRAME_HEADER.size + length])
        del buffer[: FRAME_HEADER.size + length]
        core.handle(pickle.loads(payload))


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 3:
        print(
            "usage: python -m appliance.recording.child PARAMS LEVEL json|console", file=sys.stderr
        )
        return 2
    # stdout carries the status lines; the log goes where the daemon's stderr goes.
    configure_logging(args[1], stream=sys.stderr, json=args[2] == "json")
    params, offset_ns = params_from_json(args[0])
    log.info("recorder_started", directory=str(params.directory), pid=os.getpid())
    return serve(sys.stdin.fileno(), sys.stdout, params, offset_ns)


if __name__ == "__main__":
    sys.exit(main())
