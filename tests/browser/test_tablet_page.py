"""The tablet page in headless Chromium and against hostile requests, end to end over TCP
on 127.0.0.1: pairing with the code, selecting a pallet by tapping it, the hold-to-move
button held by touch and released, a page that freezes (its beats stop: the hold lapses
within the timeout), and requests without a token, with a wrong one, replayed, flooding.

The daemon's side is a recorder of what the server asks of it (`Actions`): the hold as
the control loop would see it, each moment it changed.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import time
from collections.abc import AsyncIterator
from typing import Any

from appliance.tablet_page.gate import TabletGate, TabletParams
from appliance.tablet_page.server import TabletPage
from tests.browser.conftest import PageProblems

with contextlib.suppress(ImportError):  # the `browser` fixture fails, saying how to install it
    from playwright.async_api import Browser, Page, expect

FIRST_LOAD_S = 10.0
HOLD_TIMEOUT_S = 0.3
PALLETS = [
    {"name": "row_b.r0c1", "kind": "1200x800", "x_m": 6.2, "y_m": -2.2, "yaw_deg": 0.0,
     "length_m": 1.2, "width_m": 0.8, "from": "worker",
     "reference_area": {"x_m": 6.2, "y_m": -2.2, "radius_m": 0.8}},
    {"name": "row_a.r0c1", "kind": "1100x1100", "x_m": 4.0, "y_m": -2.5, "yaw_deg": 0.0,
     "length_m": 1.1, "width_m": 1.1, "from": "vehicle"},
]  # fmt: skip


class Actions:
    """The daemon's side: the hold as published, the selection, the state drawn."""

    def __init__(self) -> None:
        self.holds: list[tuple[float, bool, float]] = []  # (when, held, until)
        self.target: str | None = None

    def hold_changed(self, held: bool, until_s: float) -> None:
        self.holds.append((time.monotonic(), held, until_s))

    def held_at(self, t_s: float) -> bool:
        """The hold as the control loop computes it at ``t_s``: the last word, until its
        time runs out."""
        last = [h for h in self.holds if h[0] <= t_s]
        return bool(last) and last[-1][1] and t_s <= last[-1][2]

    def select(self, pallet: str) -> tuple[bool, str]:
        if pallet not in {p["name"] for p in PALLETS}:
            return False, f"no pallet {pallet!r} in the merged map"
        self.target = pallet
        return True, ""

    def state(self) -> dict[str, Any]:
        return {
            "pallets": PALLETS,
            "target": self.target,
            "path": [[-2.0, -1.5], [2.0, -6.0], [8.0, -6.0], [8.0, -2.2]],
            "vehicle": {"x_m": -2.0, "y_m": -1.5, "heading_deg": 0.0},
            "phase": "to_view" if self.target else "select",
            "mode": "READY",
        }


class Beats:
    def beat(self) -> None:
        pass


def _counter_bytes() -> Any:
    counter = itertools.count(1)
    return lambda n: next(counter).to_bytes(n, "big")


@contextlib.asynccontextmanager
async def tablet_server(actions: Actions, **params: Any) -> AsyncIterator[TabletPage]:
    gate = TabletGate(_counter_bytes(), TabletParams(hold_timeout_s=HOLD_TIMEOUT_S, **params))
    server = TabletPage(gate, actions, "127.0.0.1", 0)
    task = asyncio.ensure_future(server.run(Beats()))
    try:
        async with asyncio.timeout(10.0):
            while server.bound_port is None:
                if task.done():
                    task.result()
                await asyncio.sleep(0.01)
        yield server
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def request(
    port: int, path: str, body: object, token: str | None = None, host: str = "127.0.0.1"
) -> tuple[int, dict[str, Any]]:
    """One raw HTTP/1.1 POST, as any device on the network could send it."""
    data = json.dumps(body).encode()
    head = f"POST {path} HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Length: {len(data)}\r\n"
    if token is not None:
        head += f"Authorization: Bearer {token}\r\n"
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(head.encode() + b"\r\n" + data)
    await writer.drain()
    response = await reader.read()
    writer.close()
    status_line, _, rest = response.partition(b"\r\n")
    payload = rest.partition(b"\r\n\r\n")[2]
    try:
        document = json.loads(payload) if payload.startswith(b"{") else {}
    except ValueError:
        document = {}
    return int(status_line.split()[1]), document


async def pair(server: TabletPage) -> str:
    assert server.bound_port is not None
    status, document = await request(server.bound_port, "/api/pair", {"code": server.gate.code})
    assert status == 200, document
    return str(document["token"])


async def open_page(browser: Browser, port: int) -> tuple[Page, PageProblems]:
    context = await browser.new_context(
        viewport={"width": 900, "height": 1200}, has_touch=True, is_mobile=True
    )
    page = await context.new_page()
    problems = PageProblems()
    page.on("console", problems.on_console)
    page.on("pageerror", problems.on_page_error)
    await page.goto(f"http://127.0.0.1:{port}/")
    return page, problems


async def test_pair_select_and_hold_by_touch_then_release(browser: Browser) -> None:
    actions = Actions()
    async with tablet_server(actions) as server:
        assert server.bound_port is not None
        page, problems = await open_page(browser, server.bound_port)
        await page.fill("#code", "000000")
        await page.click("#pair")
        await expect(page.locator("#message")).to_contain_text("Not paired", timeout=5e3)
        await page.fill("#code", server.gate.code)
        await page.tap("#pair")
        await expect(page.locator("#select")).to_be_visible(timeout=FIRST_LOAD_S * 1e3)
        pallet = page.locator('#map rect[data-name="row_b.r0c1"]')
        await expect(pallet).to_be_visible(timeout=5e3)
        await pallet.tap()
        await expect(page.locator("#message")).to_have_text("Selected row_b.r0c1", timeout=5e3)
        assert actions.target == "row_b.r0c1"
        await page.tap("#guide")
        await expect(page.locator("#guidance")).to_be_visible()
        # A finger on the button: pointerdown with touch, held for a second, lifted.
        box = await page.locator("#hold").bounding_box()
        assert box is not None
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        client = await page.context.new_cdp_session(page)
        touch = {"type": "touchStart", "touchPoints": [{"x": x, "y": y, "id": 1}]}
        await client.send("Input.dispatchTouchEvent", touch)
        await asyncio.sleep(1.0)
        held_while_pressed = actions.held_at(time.monotonic())
        beats = sum(1 for _, held, _ in actions.holds if held)
        await client.send("Input.dispatchTouchEvent", {"type": "touchEnd", "touchPoints": []})
        released_at = time.monotonic()
        await asyncio.sleep(0.3)
        assert held_while_pressed, actions.holds[-5:]
        assert beats >= 7  # ten a second while held (a slow shared machine drops a few)
        # Released: the page said so at once (not by the timeout).
        release = next(h for h in actions.holds if h[0] >= released_at - 0.05 and not h[1])
        assert release[0] - released_at < 0.2
        assert not actions.held_at(time.monotonic())
        assert problems.messages == []


async def test_a_frozen_page_stops_beating_and_the_hold_lapses(browser: Browser) -> None:
    actions = Actions()
    async with tablet_server(actions) as server:
        assert server.bound_port is not None
        page, _ = await open_page(browser, server.bound_port)
        await page.fill("#code", server.gate.code)
        await page.click("#pair")
        await expect(page.locator("#select")).to_be_visible(timeout=FIRST_LOAD_S * 1e3)
        await page.click("#guide", force=True)
        await page.dispatch_event("#hold", "pointerdown", {"pointerId": 1, "isPrimary": True})
        await asyncio.sleep(0.6)
        assert actions.held_at(time.monotonic())
        # The page freezes (its timers stop, nothing more is sent): the last beat's
        # until is where the hold ends, without any word from the page.
        await page.evaluate("() => { for (let i = 1; i < 100000; i++) clearInterval(i); }")
        frozen_at = time.monotonic()
        await asyncio.sleep(HOLD_TIMEOUT_S + 0.2)
        last_until = max(until for _, held, until in actions.holds if held)
        assert last_until - frozen_at <= HOLD_TIMEOUT_S + 0.15
        assert not actions.held_at(time.monotonic())


async def test_hostile_requests_are_refused_and_move_nothing() -> None:
    actions = Actions()
    async with tablet_server(actions, burst_requests=10, max_requests_per_s=20.0) as server:
        port = server.bound_port
        assert port is not None
        # No token, a wrong one, before pairing and after.
        assert (await request(port, "/api/hold", {"seq": 1, "held": True}))[0] == 401
        token = await pair(server)
        assert (await request(port, "/api/hold", {"seq": 1, "held": True}))[0] == 401
        wrong = "0" * len(token)
        assert (await request(port, "/api/hold", {"seq": 1, "held": True}, wrong))[0] == 401
        # Another site's name for this address (DNS rebinding): refused whatever the token.
        status, _ = await request(port, "/api/hold", {"seq": 1, "held": True}, token, "evil.test")
        assert status == 421
        assert not any(held for _, held, _ in actions.holds)
        # A press, then a replay of it after the release: refused, still released.
        assert (await request(port, "/api/hold", {"seq": 5, "held": True}, token))[0] == 200
        assert (await request(port, "/api/hold", {"seq": 6, "held": False}, token))[0] == 200
        status, document = await request(port, "/api/hold", {"seq": 5, "held": True}, token)
        assert status == 409 and "replayed" in document["error"]
        assert not actions.held_at(time.monotonic())
        # Malformed bodies, a GET on the API, an oversized body.
        assert (await request(port, "/api/hold", ["not", "an", "object"], token))[0] == 400
        assert (await request(port, "/api/select", {"seq": 7, "pallet": 12}, token))[0] == 400
        big = {"seq": 8, "pallet": "x" * 5000}
        assert (await request(port, "/api/select", big, token))[0] == 413
        # A flood from the paired tablet: beyond the burst, refused with 429.
        answers = await asyncio.gather(
            *(request(port, "/api/state", {"seq": 100 + i}, token) for i in range(40))
        )
        statuses = [status for status, _ in answers]
        assert statuses.count(429) + statuses.count(503) >= 20
        # A flood of pairing guesses: locked after five, then even the right code waits.
        for _ in range(5):
            await request(port, "/api/pair", {"code": "x"})
        assert (await request(port, "/api/pair", {"code": server.gate.code}))[0] == 429
        # The server is still there for the paired tablet after it all.
        await asyncio.sleep(1.0)
        assert (await request(port, "/api/hold", {"seq": 500, "held": False}, token))[0] == 200
