"""The daemon with its views on: the operator page, the live view and the system monitor
are wired as supervised services and answer on loopback with the daemon's own state."""

from __future__ import annotations

import asyncio
import json
import shutil
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from appliance.daemon import Daemon
from appliance.modes import Mode
from tests.runtime.inline import free_port
from tests.runtime.test_daemon_control import isolated_sim_config
from tests.runtime.test_live_view import WsClient

pytestmark = pytest.mark.slow


def _get_json(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=5.0) as response:
        return json.loads(response.read())


def test_the_views_show_the_running_daemon() -> None:
    page_port, view_port = free_port(), free_port()
    config = isolated_sim_config()
    config = config.model_copy(
        update={
            "operator_page": config.operator_page.model_copy(
                update={"enabled": True, "port": page_port}
            ),
            "live_view": config.live_view.model_copy(update={"enabled": True, "port": view_port}),
        }
    )
    directory = Path(tempfile.mkdtemp(prefix="dbw-views-", dir="/tmp"))

    async def scenario() -> None:
        daemon = Daemon(config, control_socket=str(directory / "control.sock"))
        assert daemon.system_monitor is not None and daemon.live_view is not None
        run = asyncio.ensure_future(daemon.run(handle_signals=False))
        try:
            started = time.monotonic()
            while daemon.core.state.mode is not Mode.READY:
                assert time.monotonic() - started < 30.0, "READY not within 30 s"
                await asyncio.sleep(0.05)
            status = await asyncio.to_thread(_get_json, f"http://127.0.0.1:{page_port}/status.json")
            assert status["mode"] == "ready"
            assert status["vehicle"] == config.name
            assert status["system"]["disk_free_mb"] > 0  # the system monitor, in the status
            assert status["inputs"]["system.health"]["age_s"] is not None
            client = await asyncio.to_thread(WsClient, view_port)
            try:
                _, data = await asyncio.to_thread(client.frame)
                assert json.loads(data)["op"] == "serverInfo"
            finally:
                client.close()
        finally:
            daemon.request_stop("test over")
            result = await asyncio.wait_for(run, 10.0)
        assert result.exit_code == 0, result

    try:
        asyncio.run(scenario())
    finally:
        shutil.rmtree(directory, ignore_errors=True)
