"""Fixtures for running the daemon for real, with a fake systemd notify socket."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tools.fake_notify import FakeNotifySocket


@pytest.fixture
def notify_socket() -> Iterator[FakeNotifySocket]:
    # Unix socket paths are limited to 108 bytes; pytest's tmp_path can be longer.
    directory = Path(tempfile.mkdtemp(prefix="dbw-", dir="/tmp"))
    sock = FakeNotifySocket(directory)
    try:
        yield sock
    finally:
        sock.close()
        shutil.rmtree(directory, ignore_errors=True)
