"""Work too long for a control cycle, done beside it, and replayed exactly.

Planning a forklift's way to a pallet takes about a second; a control cycle has 20 ms.
A source hands such work over (`submit`) with the cycle's time as its key, keeps
stepping, and takes the result (`result`) in the first cycle whose inputs list the key
as done (``ControlInputs.jobs_done``, recorded with every cycle). The work must be a
pure function of what it was given (frozen values, no clocks), so that:

- the daemon runs it on a worker thread (`ThreadJobs`): the loop never waits for it,
  and *when* it finished is an input like a scan's arrival;
- replay and the faster-than-real-time simulation run it inline (`InlineJobs`): the
  same work, computed when the recorded inputs say it was done, gives the same result
  at the same cycle, so a replayed engagement follows the recorded plan.

A thread shares the interpreter's lock with the control loop: while a plan is computed
the loop's wake-ups can wait up to the switch interval (5 ms). Plans are asked for with
the vehicle standing (a selection, a re-plan after a stop), which is when that is
harmless; `dbw status` shows the loop's jitter either way.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from typing import Protocol

# Keys announced as done, and results kept: a source takes its result the cycle after,
# so a handful is plenty; old ones are dropped, never piled up.
KEPT = 8


@dataclass(frozen=True)
class JobOutcome:
    """The work's value, or what it raised (a bug in a planner is a refusal, not a crash)."""

    value: object = None
    error: str = ""


class Jobs(Protocol):
    def submit(self, key: float, work: Callable[[], object]) -> None: ...

    def result(self, key: float) -> JobOutcome | None: ...

    def done(self) -> tuple[float, ...]: ...


def _run(work: Callable[[], object]) -> JobOutcome:
    try:
        return JobOutcome(work())
    except Exception as exc:  # the source reports it; the loop goes on
        return JobOutcome(error=f"{type(exc).__name__}: {exc}")


class InlineJobs:
    """Every job done at once, computed when its result is asked for (replay, simulation)."""

    def __init__(self) -> None:
        self._work: dict[float, Callable[[], object]] = {}

    def submit(self, key: float, work: Callable[[], object]) -> None:
        self._work[key] = work
        while len(self._work) > KEPT:
            del self._work[min(self._work)]

    def result(self, key: float) -> JobOutcome | None:
        work = self._work.pop(key, None)
        return None if work is None else _run(work)

    def done(self) -> tuple[float, ...]:
        return tuple(sorted(self._work))


class ThreadJobs:
    """One worker thread, jobs in order; `done` is read by the control loop each cycle."""

    def __init__(self) -> None:
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dbw-jobs")
        self._lock = threading.Lock()
        self._results: dict[float, JobOutcome] = {}
        self._done: tuple[float, ...] = ()

    def submit(self, key: float, work: Callable[[], object]) -> None:
        future = self._executor.submit(_run, work)
        future.add_done_callback(partial(self._finished, key))

    def _finished(self, key: float, future: Future[JobOutcome]) -> None:
        if future.cancelled():
            return
        outcome = future.result()
        with self._lock:
            self._results[key] = outcome
            while len(self._results) > KEPT:
                del self._results[min(self._results)]
            self._done = (*self._done, key)[-KEPT:]

    def result(self, key: float) -> JobOutcome | None:
        with self._lock:
            return self._results.pop(key, None)

    def done(self) -> tuple[float, ...]:
        return self._done

    def close(self) -> None:
        """Drop what has not started; the one running finishes on its own thread."""
        self._executor.shutdown(wait=False, cancel_futures=True)
