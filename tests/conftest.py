"""Shared test setup: logs go to the captured stdout as JSON lines; hypothesis without a
per-example deadline; the runtime and browser tests marked ``realtime``.

Why the marker: ``make unit`` runs the CPU-bound tests on every core (pytest-xdist) and
then the ``realtime`` ones one at a time, because those run the daemon and its twins on
the wall clock, where a test starved of CPU by its neighbour would see stale inputs that
are not there. (Tried: the calibration maneuvers' long runs beside the others, two
groups on two workers, 495 s -> 306 s; one run in three failed, a simulated pot's frames
more than 150 ms apart: the twins are niced, and a neighbour daemon is not. Tried too:
the CPU-bound tests at nice 19 beside the realtime ones, 1,040 s -> 544 s; 13 of the 204
realtime tests failed, the daemon's loop stalled ~100 ms at a time however nice the
neighbours were: on these virtual machines a busy second core costs the first one too.)
A runtime module that only runs commands on files or faster-than-real-time simulations
says so with ``pytestmark = pytest.mark.cpu_bound``.

Why no deadline: hypothesis fails an example that takes longer than 200 ms, and on the
shared 2-core machines CI runs on the hypervisor takes up to 800 ms of CPU in one second.
A property test checks properties, not speed; speed is measured in ``benchmarks/``. The
health checks stay on: they catch strategies that generate too much or filter too much.

Why SIGINT is put back: a shell without job control (``make test &``, nohup, some CI
runners) starts a background job with SIGINT ignored, and every child inherits that, so a
test that presses Ctrl-C on a command it started (``dbw gnss record``, a calibration
step) waited in vain (seen: one run of the suite as a background job). The tests' children
start as from a terminal instead, with Python's own handler.
"""

from __future__ import annotations

import signal
import sys

import pytest
from hypothesis import settings

from appliance.logs import configure_logging

settings.register_profile("dbw", deadline=None)
settings.load_profile("dbw")


def pytest_configure(config: pytest.Config) -> None:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(autouse=True)
def _json_logs() -> None:
    configure_logging("debug", stream=sys.stdout, json=True)


REALTIME_DIRS = ("tests/runtime/", "tests/browser/")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        path = item.path.as_posix()
        in_realtime_dir = any(f"/{d}" in path for d in REALTIME_DIRS)
        if in_realtime_dir and item.get_closest_marker("cpu_bound") is None:
            item.add_marker(pytest.mark.realtime)
