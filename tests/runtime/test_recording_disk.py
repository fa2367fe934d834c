"""The recorder stops before a small disk fills: a real tmpfs, in a mount namespace of
the test's own (``unshare -rm``: no root needed where user namespaces are allowed), is
written through the recorder's file set until it refuses; the file system never filled
(no write error), the drops are counted as ``disk_low``, and what was written reads back."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

TMPFS_MB = 12


def test_the_recorder_stops_before_a_small_tmpfs_fills(tmp_path: Path) -> None:
    unshare = shutil.which("unshare")
    assert unshare, "unshare (util-linux) is needed: make test installs it"
    mount_point = tmp_path / "disk"
    mount_point.mkdir()
    script = (
        f"mount -t tmpfs -o size={TMPFS_MB}m tmpfs {mount_point} && "
        f"exec {sys.executable} -m tests.runtime.tmpfs_fill {mount_point}"
    )
    done = subprocess.run(
        [unshare, "-rm", "sh", "-c", script],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["size_bytes"] <= TMPFS_MB * 1_100_000  # it was the small disk
    assert result["state"] == "stopped", result
    assert "disk low" in result["reason"]
    assert set(result["dropped"]) == {"disk_low"}, result  # never a write error: never full
    assert result["least_free_bytes"] > 1_000_000, result
    assert result["written"] > 1000  # it recorded until the limit, not from the start
