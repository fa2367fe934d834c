"""The daemon on the simulated forklift with its tablet page on 127.0.0.1: a tablet pairs
with the code `dbw status` shows, its held button engages (hold-to-move) and keeps the
hold while it beats, a release ends the hold in the next cycle, and a tablet that stops
beating (a dropped link) loses it within the timeout. Hostile requests move nothing.
"""

from __future__ import annotations

import asyncio
import shutil
import tempfile
import time
from pathlib import Path

import pytest

from appliance.config import load_config
from appliance.daemon import Daemon, RunResult
from appliance.modes import Mode
from tests.browser.test_tablet_page import request
from tests.runtime.inline import isolated

READY_WITHIN_S = 40.0
BEAT_S = 0.1


async def _until(condition: object, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.02)


@pytest.mark.slow
async def test_a_tablet_holds_the_forklift_engaged_and_a_release_or_silence_ends_it() -> None:
    config = isolated(load_config("forklift-sim"))
    tablet = config.tablet_page.model_copy(update={"enabled": True, "port": 0})
    # The hold's mechanics, on a source that is always ready (the pallet source's own
    # flow is test_pallet_daemon's).
    engagement = config.engagement.model_copy(update={"autopilot_source": "hold_straight"})
    config = config.model_copy(update={"tablet_page": tablet, "engagement": engagement})
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")
    daemon = Daemon(config, control_socket=str(Path(directory) / "control.sock"), record=False)
    run: asyncio.Future[RunResult] = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        assert daemon.tablet is not None
        service = daemon.tablet
        await _until(lambda: daemon.core.state.mode is Mode.READY, READY_WITHIN_S)
        await _until(lambda: service.page.bound_port is not None, 5.0)
        port = service.page.bound_port
        assert port is not None
        status = daemon.status_document()["tablet"]
        assert status["paired"] is False and status["listening"] is True
        # A stranger's request, before pairing: refused, nothing held.
        assert (await request(port, "/api/hold", {"seq": 1, "held": True}, "0" * 32))[0] == 401
        code, document = await request(port, "/api/pair", {"code": status["pairing_code"]})
        assert code == 200
        token = document["token"]
        seq = 0
        # Held for a second: a beat every 0.1 s engages and holds.
        for _ in range(10):
            seq += 1
            assert (await request(port, "/api/hold", {"seq": seq, "held": True}, token))[0] == 200
            await asyncio.sleep(BEAT_S)
        assert daemon.core.state.mode in (Mode.ENGAGED, Mode.SPEED_HOLD)
        assert daemon.core.state.hold_to_move_held
        # Released: the hold ends within a cycle or two of the answer.
        seq += 1
        assert (await request(port, "/api/hold", {"seq": seq, "held": False}, token))[0] == 200
        await _until(lambda: not daemon.core.state.hold_to_move_held, 0.1)
        # Held again, then silence: the hold lapses within the timeout.
        for _ in range(5):
            seq += 1
            await request(port, "/api/hold", {"seq": seq, "held": True}, token)
            await asyncio.sleep(BEAT_S)
        assert daemon.core.state.hold_to_move_held
        silent_at = time.monotonic()
        await _until(lambda: not daemon.core.state.hold_to_move_held, 1.0)
        lapsed_after_s = time.monotonic() - silent_at
        assert lapsed_after_s <= config.tablet_page.hold_timeout_s + 0.1
        # A replay of an old beat after all that: refused, still not held.
        assert (await request(port, "/api/hold", {"seq": 3, "held": True}, token))[0] == 409
        await asyncio.sleep(0.1)
        assert not daemon.core.state.hold_to_move_held
    finally:
        daemon.request_stop("test over")
        try:
            result = await asyncio.wait_for(run, 10.0)
        finally:
            shutil.rmtree(directory, ignore_errors=True)
    assert result.exit_code == 0, result
