"""Shared test setup: logs go to the captured stdout as JSON lines; hypothesis without a
per-example deadline.

Why no deadline: hypothesis fails an example that takes longer than 200 ms, and on the
shared 2-core machines CI runs on the hypervisor takes up to 800 ms of CPU in one second.
A property test checks properties, not speed; speed is measured in ``benchmarks/``. The
health checks stay on: they catch strategies that generate too much or filter too much.
"""

from __future__ import annotations

import sys

import pytest
from hypothesis import settings

from appliance.logs import configure_logging

settings.register_profile("dbw", deadline=None)
settings.load_profile("dbw")


@pytest.fixture(autouse=True)
def _json_logs() -> None:
    configure_logging("debug", stream=sys.stdout, json=True)
