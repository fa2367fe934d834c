"""The operator page in headless Chromium, end to end: the page server on 127.0.0.1, the
page's own script polling it, and the rendered DOM read back.

A scripted status walks READY (engagement refused, with reasons) -> ENGAGED -> ERROR
(a fault, a stale input) -> ESTOP; each change must show within a second. A server that
goes away, or hangs, must make the page say the daemon is not reachable instead of
showing the last status as if it were fresh; one that comes back must show live data
again. The last test runs the real daemon on the simulated flat-bed with the page beside
it, as the daemon will.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import re
import shutil
import tempfile
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest

from appliance.config import load_config
from appliance.daemon import Daemon, RunResult
from appliance.modes import Mode
from appliance.operator_page import OperatorPage, scans_document
from tests.browser.conftest import PageProblems
from tests.runtime.inline import isolated

with contextlib.suppress(ImportError):  # the `browser` fixture fails, saying how to install it
    from playwright.async_api import Browser, Page, expect

CHANGE_SHOWN_S = 1.0  # the requirement: a change in the status is on screen within 1 s
FIRST_LOAD_S = 10.0  # the browser's first page load on a shared machine
UNREACHABLE_SHOWN_S = 5.0  # the page's fetch deadline (1.5 s) plus room
DAEMON_READY_S = 40.0
SCANS_SHOWN_S = 5.0
ENGAGE_WITHIN_S = 30.0
REFUSAL = "outside the automatic zone: 14.2 m out (at most 12)"


def status_doc(mode: str, **changes: Any) -> dict[str, Any]:
    """A status document shaped as `Daemon.status_document()` makes it."""
    doc: dict[str, Any] = {
        "vehicle": "flatbed-sim",
        "uptime_s": 12.5,
        "mode": mode,
        "mode_since_s": 0.4,
        "set_speed_mps": None,
        "measured_speed_mps": 0.0,
        "estop_latched": False,
        "last_refusal": [],
        "engage_blockers": [],
        "faults": [],
        "commands": {"steering": "released", "brake": "released", "pc104": "STOP"},
        "inputs": {
            "steering.pot": {"age_s": 0.003, "limit_s": 0.05, "stale": False, "critical": True},
            "scan.left": {"age_s": 0.011, "limit_s": 0.12, "stale": False, "critical": True},
        },
        "autopilot": {
            "source": "dock",
            "localization": {
                "status": "ok",
                "quality": 95,
                "pose": {
                    "x_m": -15.0,
                    "y_m": 0.39,
                    "heading_deg": 3.0,
                    "sigma_x_m": 0.001,
                    "sigma_y_m": 0.011,
                    "sigma_heading_deg": 0.04,
                },
            },
            "docking": {"gap_m": 9.01, "lateral_m": 0.707, "phase": "ready"},
        },
    }
    doc.update(changes)
    return doc


class ScriptedStatus:
    """The status callable; the test sets what it answers next."""

    def __init__(self, doc: dict[str, Any]) -> None:
        self.doc = doc

    def __call__(self) -> dict[str, Any]:
        return copy.deepcopy(self.doc)


def fake_scans() -> dict[str, Any]:
    return {
        "frame": "vehicle",
        "scans": {"left": {"age_s": 0.02, "points_m": [[6.0, y / 10.0] for y in range(-30, 30)]}},
    }


class Beats:
    def beat(self) -> None:
        pass


@contextlib.asynccontextmanager
async def page_server(
    status: Callable[[], dict[str, Any]],
    scans: Callable[[], dict[str, Any]] | None = fake_scans,
    port: int = 0,
) -> AsyncIterator[OperatorPage]:
    server = OperatorPage(status, scans, "127.0.0.1", port)
    task = asyncio.ensure_future(server.run(Beats()))
    try:
        async with asyncio.timeout(10.0):
            while server.bound_port is None:
                if task.done():
                    task.result()  # raises why it could not listen
                await asyncio.sleep(0.01)
        yield server
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@contextlib.asynccontextmanager
async def silent_server(port: int) -> AsyncIterator[None]:
    """Accepts connections on ``port`` and never answers: a hung daemon."""
    held: list[asyncio.StreamWriter] = []

    async def hold(_: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        held.append(writer)

    server = await asyncio.start_server(hold, "127.0.0.1", port, reuse_address=True)
    try:
        yield
    finally:
        server.close()
        for writer in held:
            writer.transport.abort()


async def open_page(browser: Browser, port: int) -> tuple[Page, PageProblems]:
    page = await browser.new_page(viewport={"width": 1400, "height": 1400})
    problems = PageProblems()
    page.on("console", problems.on_console)
    page.on("pageerror", problems.on_page_error)
    await page.goto(f"http://127.0.0.1:{port}/")
    return page, problems


async def test_the_page_follows_the_daemon_through_its_modes(browser: Browser) -> None:
    status = ScriptedStatus(status_doc("ready", engage_blockers=[REFUSAL], last_refusal=[REFUSAL]))
    async with page_server(status) as server:
        assert server.bound_port is not None
        page, problems = await open_page(browser, server.bound_port)
        mode, by_id = page.get_by_test_id("mode"), page.get_by_test_id
        await expect(by_id("connection")).to_have_attribute(
            "data-state", "live", timeout=FIRST_LOAD_S * 1e3
        )
        await expect(mode).to_have_attribute("data-mode", "ready", timeout=FIRST_LOAD_S * 1e3)
        await expect(mode).to_have_text("READY")
        await expect(by_id("engage-verdict")).to_have_text("engage now: would be refused")
        await expect(by_id("engage-blockers")).to_contain_text(REFUSAL)
        await expect(by_id("last-refusal")).to_contain_text(REFUSAL)
        # The dock view drew the launcher and the vehicle at its pose; the scans drew.
        await expect(by_id("dock")).to_be_visible()
        await expect(by_id("dock-view")).to_have_attribute("data-drawn", "launcher,vehicle")
        await expect(by_id("localization")).to_contain_text("x -15.000 m ±0.001")
        await expect(by_id("scans-view")).to_have_attribute("data-points", "60")

        status.doc = status_doc("engaged", mode_since_s=0.0)
        await expect(mode).to_have_attribute("data-mode", "engaged", timeout=CHANGE_SHOWN_S * 1e3)
        await expect(mode).to_have_text("ENGAGED")

        error = status_doc(
            "error",
            faults=[
                {
                    "key": "stale:steering.pot",
                    "detail": "steering.pot 61 ms old (limit 50 ms)",
                    "since_s": 0.1,
                }
            ],
            engage_blockers=["cannot engage from error"],
        )
        error["inputs"]["steering.pot"].update(age_s=0.061, stale=True)
        status.doc = error
        pot = by_id("input-steering.pot")
        await expect(mode).to_have_attribute("data-mode", "error", timeout=CHANGE_SHOWN_S * 1e3)
        await expect(by_id("fault")).to_contain_text(
            "stale:steering.pot: steering.pot 61 ms old (limit 50 ms)",
            timeout=CHANGE_SHOWN_S * 1e3,
        )
        await expect(pot).to_have_attribute("data-stale", "true", timeout=CHANGE_SHOWN_S * 1e3)
        await expect(pot).to_contain_text("STALE")
        await expect(by_id("input-scan.left")).to_have_attribute("data-stale", "false")

        estop = status_doc("estop", estop_latched=True, engage_blockers=["e-stop latched"])
        estop["inputs"]["scan.left"].update(age_s=None, stale=True)
        status.doc = estop
        await expect(mode).to_have_attribute("data-mode", "estop", timeout=CHANGE_SHOWN_S * 1e3)
        await expect(by_id("estop")).to_be_visible(timeout=CHANGE_SHOWN_S * 1e3)
        await expect(by_id("input-scan.left")).to_contain_text("never")
        await expect(by_id("faults")).to_have_text("none")
        await expect(by_id("connection")).to_have_attribute("data-state", "live")
        assert problems.messages == []


async def test_the_page_says_when_the_daemon_is_not_reachable(browser: Browser) -> None:
    status = ScriptedStatus(status_doc("ready"))
    async with page_server(status, scans=None) as server:
        port = server.bound_port
        assert port is not None
        page, problems = await open_page(browser, port)
        connection = page.get_by_test_id("connection")
        await expect(connection).to_have_attribute("data-state", "live", timeout=FIRST_LOAD_S * 1e3)
        await expect(page.get_by_test_id("scans-info")).to_have_text("this daemon serves no scans")
    # Gone: connections refused.
    await expect(connection).to_contain_text(
        "daemon not reachable", timeout=UNREACHABLE_SHOWN_S * 1e3
    )
    await expect(page.get_by_test_id("status-age")).to_contain_text("last good status")
    await expect(page.get_by_test_id("mode")).to_have_class("stale")
    await expect(page.locator("main")).to_have_class("stale-data")
    # Back, in another mode: live again, showing the new status.
    status.doc = status_doc("engaged")
    async with page_server(status, scans=None, port=port):
        await expect(connection).to_have_attribute(
            "data-state", "live", timeout=UNREACHABLE_SHOWN_S * 1e3
        )
        await expect(page.get_by_test_id("mode")).to_have_attribute("data-mode", "engaged")
        await expect(page.get_by_test_id("mode")).not_to_have_class("stale")
    # Hung: accepts and never answers.
    async with silent_server(port):
        await expect(connection).to_contain_text(
            "daemon not reachable", timeout=UNREACHABLE_SHOWN_S * 1e3
        )
        await expect(connection).to_contain_text("no answer within")
    assert problems.messages == []


@pytest.mark.slow
async def test_the_page_beside_the_real_daemon_shows_ready_then_engaged(browser: Browser) -> None:
    config = isolated(load_config("flatbed-sim"))
    directory = tempfile.mkdtemp(prefix="dbw-", dir="/tmp")
    daemon = Daemon(config, control_socket=str(Path(directory) / "control.sock"), record=False)
    run: asyncio.Future[RunResult] = asyncio.ensure_future(daemon.run(handle_signals=False))
    try:
        async with page_server(
            daemon.status_document, lambda: scans_document(daemon.io.topics, daemon.clock())
        ) as server:
            assert server.bound_port is not None
            page, problems = await open_page(browser, server.bound_port)
            mode = page.get_by_test_id("mode")
            await operate_until_shown(page, daemon, Mode.READY, hand_back, DAEMON_READY_S)
            await operate_until_shown(page, daemon, Mode.ENGAGED, engage, ENGAGE_WITHIN_S)
            await expect(mode).to_have_text("ENGAGED")
            await expect(page.get_by_test_id("input-steering.pot")).to_be_visible()
            await expect(page.get_by_test_id("dock-view")).to_have_attribute(
                "data-drawn", "launcher,vehicle"
            )
            # The scanners' last scans, drawn (the page polls them twice a second).
            await expect(page.get_by_test_id("scans-view")).to_have_attribute(
                "data-points", re.compile(r"^[1-9][0-9]*$"), timeout=SCANS_SHOWN_S * 1e3
            )
            assert problems.messages == []
    finally:
        daemon.request_stop("test over")
        try:
            result = await asyncio.wait_for(run, 10.0)
        finally:
            shutil.rmtree(directory, ignore_errors=True)
    assert result.exit_code == 0, result


def hand_back(daemon: Daemon) -> None:
    """The operator's manual override: an ERROR left by an input late on a loaded machine
    (the fault already cleared) goes back to READY."""
    state = daemon.core.state
    if state.mode is Mode.ERROR and not state.faults:
        daemon.core.request("disengage", daemon.clock())


def engage(daemon: Daemon) -> None:
    """ENGAGE once docking allows it (in the automatic zone, a good pose)."""
    hand_back(daemon)
    if daemon.core.state.mode is Mode.READY and not daemon.core.engage_blockers():
        daemon.core.request("engage", daemon.clock())


async def operate_until_shown(
    page: Page, daemon: Daemon, mode: Mode, operate: Callable[[Daemon], None], timeout_s: float
) -> None:
    """Operate the daemon into ``mode``; once it is there the page must show it within
    ``CHANGE_SHOWN_S`` (twice that: the real daemon's status, a loaded machine). On a
    loaded machine the daemon may fall out of the mode (a late input is a fault) before
    the page could show it: then operate again. A daemon that stays in the mode for the
    whole window and a page that does not show it fail the test."""
    shown_within_ms = 2 * CHANGE_SHOWN_S * 1e3
    deadline_s = time.monotonic() + timeout_s
    while time.monotonic() < deadline_s:
        operate(daemon)
        if daemon.core.state.mode is mode:
            entered_s = daemon.core.mode_since_s
            try:
                await expect(page.get_by_test_id("mode")).to_have_attribute(
                    "data-mode", str(mode), timeout=shown_within_ms
                )
                return
            except AssertionError:
                if daemon.core.mode_since_s == entered_s and daemon.core.state.mode is mode:
                    raise  # the daemon stayed; the page did not follow
        await asyncio.sleep(0.05)
    pytest.fail(f"the daemon did not reach {mode} within {timeout_s} s: {daemon.status_line()}")
