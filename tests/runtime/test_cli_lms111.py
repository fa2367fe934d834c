"""`dbw lms111 probe/record/decode` against the simulated scanner, as a person runs them."""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

from appliance.sim.site_file import load_site
from appliance.sim.twins.lms111 import Lms111Twin
from drivers.geometry import Pose2D


async def dbw(*args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "appliance",
        "--log-format",
        "json",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


async def test_probe_record_and_decode(tmp_path: Path) -> None:
    twin = Lms111Twin(
        load_site("launcher"), Pose2D(2.6, 1.1, 0.78), lambda _t: Pose2D(-12.6, 0.0, 0.0)
    )
    await twin.start()
    endpoint = f"127.0.0.1:{twin.port}"
    try:
        code, out, err = await dbw("lms111", "probe", endpoint)
        assert code == 0, err
        identity = json.loads(out)
        assert identity["port"] == twin.port
        assert identity["status"] is not None

        recording = tmp_path / "left.lms"
        code, out, err = await dbw("lms111", "record", endpoint, str(recording), "--seconds", "1")
        assert code == 0, err
        stats = json.loads(out)
        assert stats["scans"] >= 40

        code, out, err = await dbw("lms111", "decode", str(recording), "--json")
        assert code == 0, err
        lines = [json.loads(line) for line in out.splitlines()]
        scans, summary = lines[:-1], lines[-1]
        assert len(scans) == summary["scans"] == stats["scans"]
        assert summary["dropped_scans"] == 0
        assert all(s["valid_beams"] > 0 for s in scans)
    finally:
        await twin.stop()


async def test_bad_endpoint_and_unreachable_scanner_are_clear() -> None:
    code, _, err = await dbw("lms111", "probe", "nonsense")
    assert code == 2
    assert "HOST:PORT" in err
    code, _, err = await dbw("lms111", "probe", "127.0.0.1:9", "--timeout-s", "0.5")
    assert code == 1
    assert "Traceback" not in err


async def test_decode_of_a_file_that_is_not_a_recording(tmp_path: Path) -> None:
    junk = tmp_path / "junk.lms"
    junk.write_bytes(b"not a recording at all\n")
    code, _, err = await dbw("lms111", "decode", str(junk))
    assert code == 2
    assert "Traceback" not in err
