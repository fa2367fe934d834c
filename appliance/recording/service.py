"""The daemon's side of the recorder: taps every sample, cycle and request, never blocks.

What is recorded: every sample of every topic as it is published (boards, PC104, scans,
GNSS epochs), every control cycle (the time, the inputs the core saw with the scans by
their sample's seq, the output), every request the control socket hands the core, and
each (re)start of the core. Replay (`appliance/recording/replay.py`) needs exactly these.

The cost on the event loop is one ``pickle.dumps`` and one buffered pipe write per
message; the encoding, compression and disk work happen in the recorder's process
(`appliance/recording/child.py`). Nothing here waits: a message that would grow the
pipe's backlog past ``max_backlog_mb`` is dropped and counted by kind, as is one sent
while the child is not running (before it starts the first messages wait in a bounded
queue, so the core's first cycle is in the file). The counts go into the recording
(``/dbw/recorder``) and ``dbw status``.

A recorder that dies is restarted by the supervisor with backoff; it is not critical:
the vehicle drives without it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import pickle
import struct
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from appliance import __version__
from appliance.config import VehicleConfig
from appliance.config.loader import to_toml
from appliance.core.inputs import ControlInputs
from appliance.core.output import CoreOutput
from appliance.logs import current_log_settings, get_logger
from appliance.sim_process import lower_priority
from appliance.supervisor import ServiceContext
from appliance.topics import TopicRegistry
from drivers.lms111.mounted import MountedScan
from drivers.topics import Sample

log = get_logger("recording")

FRAME_HEADER = struct.Struct("<I")
STOP_GRACE_S = 1.5  # the child finishes its file (summary, indexes) on end of file
RECORDER_NICE_INCREMENT = 5
# Topics not recorded as samples: the control status is every cycle's output, which the
# cycle record holds already.
UNRECORDED_TOPICS = frozenset({"control.status"})
# Scan samples remembered per side so a cycle can name the scan it saw by its seq.
SCANS_REMEMBERED = 8


def recording_directory(config: VehicleConfig) -> Path:
    rec = config.recording
    return Path(rec.directory) if rec.directory else Path(config.paths.state_dir) / "recordings"


def child_params(config: VehicleConfig, clock_offset_ns: int) -> dict[str, Any]:
    rec = config.recording
    return {
        "directory": str(recording_directory(config).resolve()),
        "split_size_bytes": int(rec.split_size_mb * 1e6),
        "split_duration_ns": int(rec.split_duration_s * 1e9),
        "quota_bytes": int(rec.quota_mb * 1e6),
        "warn_free_bytes": int(rec.warn_free_mb * 1e6),
        "stop_free_bytes": int(rec.stop_free_mb * 1e6),
        "flush_interval_ns": int(rec.flush_interval_s * 1e9),
        "clock_offset_ns": clock_offset_ns,
    }


def session_metadata(
    config: VehicleConfig, calibration_text: str, calibration_problem: str, clock_offset_ns: int
) -> dict[str, dict[str, str]]:
    """What replay needs besides the messages: the vehicle file, the calibration, and
    how the log times relate to the monotonic times inside the messages."""
    return {
        "dbw": {
            "version": __version__,
            "session": uuid.uuid4().hex,
            "vehicle": config.name,
            "python": sys.version.split()[0],
            "clock_offset_ns": str(clock_offset_ns),
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
        "dbw.config": {"toml": to_toml(config.model_dump(mode="json"))},
        "dbw.calibration": {
            "toml": calibration_text,
            "problem": calibration_problem,
            "source": str(config.paths.calibration_file),
        },
    }


@dataclass
class RecorderCounts:
    sent: int = 0
    dropped: dict[str, int] | None = None

    def drop(self, kind: str) -> None:
        if self.dropped is None:
            self.dropped = {}
        self.dropped[kind] = self.dropped.get(kind, 0) + 1


class Recorder:
    """Taps the daemon's topics and control loop, and runs the recorder's process."""

    def __init__(
        self,
        config: VehicleConfig,
        calibration_text: str,
        *,
        calibration_problem: str = "",
        clock: Callable[[], float] = time.monotonic,
        python: str = sys.executable,
    ) -> None:
        self.config = config
        self._clock = clock
        self.python = python
        self.clock_offset_ns = time.time_ns() - time.monotonic_ns()
        self.metadata = session_metadata(
            config, calibration_text, calibration_problem, self.clock_offset_ns
        )
        self.max_backlog_bytes = int(config.recording.max_backlog_mb * 1e6)
        self.counts = RecorderCounts()
        self.child_status: dict[str, Any] = {}
        self._writer: asyncio.StreamWriter | None = None
        self._pending: list[bytes] = []
        self._pending_bytes = 0
        self._started_once = False
        self._scan_seqs: dict[str, list[tuple[MountedScan, int]]] = {}
        self._proc: asyncio.subprocess.Process | None = None

    # ---- taps (called on the event loop; they never wait) ------------------------------
    def attach(self, topics: TopicRegistry) -> None:
        for name, topic in topics.items():
            if name not in UNRECORDED_TOPICS:
                topic.subscribe(self._sample_listener(name))

    def _sample_listener(self, name: str) -> Callable[[Sample[Any]], None]:
        side = name.removeprefix("scan.") if name.startswith("scan.") else None

        def listener(sample: Sample[Any]) -> None:
            if side is not None and isinstance(sample.value, MountedScan):
                remembered = self._scan_seqs.setdefault(side, [])
                remembered.append((sample.value, sample.seq))
                del remembered[:-SCANS_REMEMBERED]
            self._send(
                "sample",
                ("sample", self._log_ns(), name, sample.seq, sample.stamp_s, sample.value),
            )

        return listener

    def attach_raw(self, sources: list[tuple[str, str, list[Any]]]) -> None:
        """Every link's raw input (`VehicleIO.raw_sources`): bytes as read, CAN frames
        as received, each with its receive time."""
        for name, kind, listeners in sources:
            listeners.append(
                self._can_listener(name) if kind == "can" else self._bytes_listener(name)
            )

    def _bytes_listener(self, name: str) -> Callable[[bytes, float], None]:
        def listener(data: bytes, receive_time_s: float) -> None:
            self._send("raw", ("raw", self._log_ns(), name, "bytes", bytes(data), receive_time_s))

        return listener

    def _can_listener(self, name: str) -> Callable[[Any, float], None]:
        def listener(message: Any, receive_time_s: float) -> None:
            frame = (
                int(message.arbitration_id),
                bool(message.is_extended_id),
                bool(message.is_error_frame),
                bool(message.is_remote_frame),
                int(message.dlc),
                bytes(message.data),
            )
            self._send("raw", ("raw", self._log_ns(), name, "can", frame, receive_time_s))

        return listener

    def on_cycle(self, now_s: float, inputs: ControlInputs, output: CoreOutput) -> None:
        scan_seqs: dict[str, int | None] = {}
        inline = {}
        for side, scan in inputs.scans.items():
            seq = None
            if scan is not None:
                seq = next((s for obj, s in self._scan_seqs.get(side, ()) if obj is scan), None)
                if seq is None:  # a scan that never went through a topic: keep it whole
                    inline[side] = scan
            scan_seqs[side] = seq
        slim = replace(inputs, scans=inline)
        self._send("cycle", ("cycle", self._log_ns(), now_s, slim, scan_seqs, output))

    def on_core_reset(self, now_s: float) -> None:
        self._send("reset", ("reset", self._log_ns(), now_s))

    def on_request(
        self, kind: str, name: str, now_s: float | None, accepted: bool, message: str
    ) -> None:
        self._send("request", ("request", self._log_ns(), now_s, kind, name, accepted, message))

    def _log_ns(self) -> int:
        return int(self._clock() * 1e9) + self.clock_offset_ns

    def _send(self, kind: str, frame: tuple[Any, ...]) -> None:
        writer = self._writer
        if writer is None or writer.is_closing():
            if self._started_once or self._pending_bytes > self.max_backlog_bytes:
                self.counts.drop(kind)
                return
            data = _frame(frame)
            self._pending.append(data)
            self._pending_bytes += len(data)
            return
        if writer.transport.get_write_buffer_size() > self.max_backlog_bytes:
            self.counts.drop(kind)
            return
        writer.write(_frame(frame))
        self.counts.sent += 1

    @property
    def pid(self) -> int | None:
        """The recorder process's pid while it runs (benchmarks count its CPU)."""
        proc = self._proc
        return None if proc is None or proc.returncode is not None else proc.pid

    def status(self) -> dict[str, Any]:
        return {
            "directory": str(recording_directory(self.config)),
            "running": self._writer is not None,
            "sent": self.counts.sent,
            "dropped_in_daemon": dict(self.counts.dropped or {}),
            **{k: v for k, v in self.child_status.items() if k != "directory"},
        }

    # ---- the service ---------------------------------------------------------------------
    def command(self) -> list[str]:
        level, as_json = current_log_settings()
        params = json.dumps(child_params(self.config, self.clock_offset_ns))
        return [
            self.python,
            "-m",
            "appliance.recording.child",
            params,
            level,
            "json" if as_json else "console",
        ]

    async def run(self, ctx: ServiceContext) -> None:
        proc = await asyncio.create_subprocess_exec(
            *self.command(), stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE
        )
        assert proc.stdin is not None and proc.stdout is not None
        self._proc = proc
        lower_priority(proc.pid, RECORDER_NICE_INCREMENT)
        writer = proc.stdin
        try:
            writer.write(_frame(("meta", self.metadata)))
            for data in self._pending:
                writer.write(data)
            self.counts.sent += len(self._pending)
            self._pending.clear()
            self._pending_bytes = 0
            self._writer = writer
            self._started_once = True
            log.info("recorder_running", pid=proc.pid, directory=self.child_params_dir())
            while line := await proc.stdout.readline():
                with contextlib.suppress(ValueError):
                    self.child_status = json.loads(line)
                ctx.beat()
                self._send("counts", ("counts", self._log_ns(), dict(self.counts.dropped or {})))
            code = await proc.wait()
            raise RuntimeError(f"the recorder's process ended (exit code {code})")
        finally:
            self._writer = None
            await _stop(proc, writer)

    def child_params_dir(self) -> str:
        return str(recording_directory(self.config))

    async def close(self, timeout_s: float = STOP_GRACE_S) -> bool:
        """Stop recording: end of file to the child, and wait (bounded) until it has
        finished its file, so the daemon's last file ends with its summary. False if it
        had not finished by then (it goes on finishing by itself)."""
        writer, self._writer = self._writer, None
        self._started_once = True  # from now on, whatever is sent is dropped and counted
        if writer is not None:
            with contextlib.suppress(OSError, RuntimeError):
                writer.close()
        proc = self._proc
        if proc is None or proc.returncode is not None:
            return True
        try:
            await asyncio.wait_for(asyncio.shield(proc.wait()), timeout_s)
        except TimeoutError:
            log.warning("recorder_slow_to_finish", pid=proc.pid, waited_s=timeout_s)
            return False
        return True


def _frame(frame: tuple[Any, ...]) -> bytes:
    data = pickle.dumps(frame, protocol=pickle.HIGHEST_PROTOCOL)
    return FRAME_HEADER.pack(len(data)) + data


async def _stop(proc: asyncio.subprocess.Process, writer: asyncio.StreamWriter) -> None:
    """End of file lets the child finish its file and exit. The daemon does not wait for
    it here (a cancelled service must end within the shutdown grace; `Recorder.close`
    waits, bounded, before that): a child left finishing exits by itself."""
    with contextlib.suppress(OSError, RuntimeError):
        writer.close()
    if proc.returncode is None:
        log.info("recorder_finishing", pid=proc.pid)
