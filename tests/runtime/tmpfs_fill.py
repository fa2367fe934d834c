"""Fill a small file system through the recorder's file set; print what happened (JSON).

Run by tests/runtime/test_recording_disk.py inside a mount namespace of its own with a
small tmpfs over DIRECTORY (``unshare -rm``), so the disk that fills is the test's own.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

from appliance.recording.files import ChannelSpec, FileSetParams, RecordingFiles

MB = 1_000_000
SPEC = ChannelSpec("/dbw/topic/noise", "dbw.sample:any", b'{"type": "object"}')


def main(directory: str) -> int:
    params = FileSetParams(
        directory=Path(directory) / "recordings",
        split_size_bytes=2 * MB,
        split_duration_ns=3600 * 10**9,
        quota_bytes=10**12,  # the quota is not what stops it here: the disk is
        warn_free_bytes=5 * MB,
        stop_free_bytes=4 * MB,
        flush_interval_ns=10**9,
    )
    files = RecordingFiles(params, {"dbw": {"session": "tmpfs"}}, lambda: "20260101T000000Z")
    least_free = shutil.disk_usage(directory).free
    written = dropped = 0
    t_ns = 0
    while dropped < 200:  # well past the point where it must have stopped
        data = json.dumps({"noise": os.urandom(3000).hex()}).encode()  # does not compress
        t_ns += 10_000_000  # 100 messages a second of log time: 0.6 MB/s
        if files.write(SPEC, t_ns, data, written + dropped):
            written += 1
        else:
            dropped += 1
        least_free = min(least_free, shutil.disk_usage(directory).free)
    files.close()
    print(
        json.dumps(
            {
                "state": files.state,
                "reason": files.reason,
                "written": written,
                "dropped": dict(files.counts.dropped),
                "least_free_bytes": least_free,
                "size_bytes": shutil.disk_usage(directory).total,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
