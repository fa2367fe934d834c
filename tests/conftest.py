"""Shared test setup: logs go to the captured stdout as JSON lines."""

from __future__ import annotations

import sys

import pytest

from appliance.logs import configure_logging


@pytest.fixture(autouse=True)
def _json_logs() -> None:
    configure_logging("debug", stream=sys.stdout, json=True)
