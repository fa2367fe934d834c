"""Replacing a file whole, or not at all.

Another process may be waiting for a file to appear (the daemon for `dbw sim
--write-config`), and the vehicle may lose power mid-write: a partly written vehicle or
calibration file would parse as a different, valid-looking one with its missing sections
defaulted.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def write_text_atomic(path: str | Path, text: str) -> None:
    """Replace ``path`` by ``text`` so that a reader sees the old file or the new one, whole.

    Another process may be waiting for the file to appear (the daemon for `dbw sim
    --write-config`), and the vehicle may lose power mid-write: a partly written file would
    parse as a different, valid-looking configuration with its missing sections defaulted.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp_name, 0o644)  # mkstemp makes it 0600; the service user must read it
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise
    _fsync_directory(path.parent)


def _fsync_directory(directory: Path) -> None:
    """Make the rename itself durable: the vehicle may lose power right after a write."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)
