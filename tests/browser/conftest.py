"""Headless Chromium for the operator page's tests: Debian's chromium driven by Playwright.

No browser is downloaded (`playwright install` is never run): the tests use the system's
``/usr/bin/chromium`` (``DBW_CHROMIUM`` overrides the path). Without it, or without the
playwright package, the tests fail, saying how to get them; they are never skipped.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import AsyncIterator
from typing import Any

import pytest

try:
    from playwright.async_api import Browser, async_playwright
except ImportError:  # reported by the fixture, as a failure with the fix
    async_playwright = None

CHROMIUM = os.environ.get("DBW_CHROMIUM", "/usr/bin/chromium")
INSTALL_HINT = (
    "`make test` installs it (Debian package `chromium`, Python package `playwright` from "
    "the dev extras); by hand: `sudo apt-get install chromium` and "
    "`.venv/bin/pip install -e '.[dev]'`"
)


@pytest.fixture
async def browser() -> AsyncIterator[Browser]:
    if async_playwright is None:
        pytest.fail("the browser tests need the Python package playwright: " + INSTALL_HINT)
    if not (os.access(CHROMIUM, os.X_OK) or shutil.which(CHROMIUM)):
        pytest.fail(f"the browser tests need Chromium at {CHROMIUM}: " + INSTALL_HINT)
    async with async_playwright() as playwright:
        launched = await playwright.chromium.launch(
            executable_path=CHROMIUM, headless=True, chromium_sandbox=False
        )
        try:
            yield launched
        finally:
            await launched.close()


class PageProblems:
    """Script errors and Content-Security-Policy violations a page reported."""

    def __init__(self) -> None:
        self.messages: list[str] = []

    def on_console(self, message: Any) -> None:
        text = str(message.text)
        if message.type == "error" and "Failed to load resource" not in text:
            self.messages.append(text)  # a 404 for /favicon.ico is expected and harmless
        elif "Content Security Policy" in text:
            self.messages.append(text)

    def on_page_error(self, error: Any) -> None:
        self.messages.append(f"uncaught: {error}")
