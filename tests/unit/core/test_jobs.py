"""Background jobs (`appliance.core.jobs`): a result is taken only once its key is listed
as done, inline and threaded give the same values, a failing job is an error, not a
crash, and what is kept stays bounded."""

from __future__ import annotations

import threading
import time

from hypothesis import given
from hypothesis import strategies as st

from appliance.core.jobs import KEPT, InlineJobs, JobOutcome, ThreadJobs


def _square(x: int) -> int:
    return x * x


def _fail() -> object:
    raise ValueError("no way")


def test_inline_jobs_are_done_at_once_and_computed_when_taken() -> None:
    calls: list[int] = []
    jobs = InlineJobs()

    def work() -> int:
        calls.append(1)
        return 7

    jobs.submit(1.5, work)
    assert jobs.done() == (1.5,) and calls == []
    assert jobs.result(1.5) == JobOutcome(7)
    assert calls == [1]
    assert jobs.result(1.5) is None  # taken once
    assert jobs.done() == ()


def test_a_failing_job_is_an_outcome_with_the_error() -> None:
    for jobs in (InlineJobs(), ThreadJobs()):
        jobs.submit(2.0, _fail)
        deadline = time.monotonic() + 5.0
        while 2.0 not in jobs.done():
            assert time.monotonic() < deadline
            time.sleep(0.001)
        outcome = jobs.result(2.0)
        assert outcome is not None and outcome.value is None
        assert outcome.error == "ValueError: no way"


def test_threaded_jobs_run_off_the_caller_in_order_and_say_when_done() -> None:
    jobs = ThreadJobs()
    gate = threading.Event()
    jobs.submit(1.0, gate.wait)
    jobs.submit(2.0, lambda: _square(3))
    time.sleep(0.05)
    assert jobs.done() == ()  # the first waits, the second is behind it
    gate.set()
    deadline = time.monotonic() + 5.0
    while jobs.done() != (1.0, 2.0):
        assert time.monotonic() < deadline
        time.sleep(0.001)
    assert jobs.result(2.0) == JobOutcome(9)
    assert jobs.result(1.0) == JobOutcome(True)
    jobs.close()


@given(st.lists(st.integers(0, 1000), min_size=1, max_size=30))
def test_inline_and_threaded_give_the_same_values_and_keep_few(values: list[int]) -> None:
    inline, threaded = InlineJobs(), ThreadJobs()
    for i, value in enumerate(values):
        inline.submit(float(i), lambda v=value: _square(v))
        threaded.submit(float(i), lambda v=value: _square(v))
    last = float(len(values) - 1)
    deadline = time.monotonic() + 5.0
    while last not in threaded.done():
        assert time.monotonic() < deadline
        time.sleep(0.0005)
    assert len(inline.done()) <= KEPT and len(threaded.done()) <= KEPT
    for key in inline.done():
        assert key in threaded.done()
        assert inline.result(key) == threaded.result(key) == JobOutcome(values[int(key)] ** 2)
    threaded.close()
