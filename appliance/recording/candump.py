"""The CAN traffic also as a candump log, beside each MCAP file, through python-can.

Why a second copy: the CAN people on a vehicle project read candump logs with the tools
they have (``canplayer``, ``cansniffer``-style scripts, python-can's ``LogReader``), and
a candump line is what a bug report about the PC104 link gets. python-can's own
``CanutilsLogWriter`` writes it; the file is named after the MCAP file it belongs to
(``dbw-...-000.mcap`` -> ``dbw-...-000.can.log``) and starts anew with each MCAP file.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import can

from appliance.logs import get_logger

log = get_logger("recording")

CANDUMP_SUFFIX = ".can.log"
CHANNEL = "pc104"


def candump_path(mcap_path: Path) -> Path:
    return mcap_path.with_suffix(CANDUMP_SUFFIX)


class CandumpLog:
    """Frames to the candump log of the MCAP file being written (none: not written)."""

    def __init__(self) -> None:
        self._writer: Any = None
        self._for: Path | None = None
        self.frames = 0

    def write(self, frame: Any, log_time_ns: int, mcap_path: Path | None) -> None:
        if mcap_path is None:
            return
        if mcap_path != self._for:
            self.close()
            try:
                self._writer = can.CanutilsLogWriter(str(candump_path(mcap_path)), CHANNEL)
            except OSError as exc:
                log.error("candump_open_failed", path=str(candump_path(mcap_path)), error=str(exc))
                return
            self._for = mcap_path
        can_id, ext, err, rtr, dlc, data = frame
        message = can.Message(
            timestamp=log_time_ns / 1e9,
            arbitration_id=can_id,
            is_extended_id=ext,
            is_error_frame=err,
            is_remote_frame=rtr,
            dlc=dlc,
            data=data,
            channel=CHANNEL,
        )
        try:
            self._writer.on_message_received(message)
            self.frames += 1
        except (OSError, ValueError) as exc:
            log.error("candump_write_failed", error=str(exc))
            self.close()

    def flush(self) -> None:
        if self._writer is not None:
            with contextlib.suppress(OSError, ValueError):
                self._writer.file.flush()

    def close(self) -> None:
        writer, self._writer, self._for = self._writer, None, None
        if writer is not None:
            with contextlib.suppress(OSError, ValueError):
                writer.stop()
