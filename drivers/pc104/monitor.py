"""Receive-side checks of one periodic message: counter, CRC failures, period, staleness.

One :class:`ReceiveMonitor` watches one identifier. It is pure (time is an argument) and
small, so the client, the twin and the tests share it. It answers two questions: may this
frame be used (``update`` returns ACCEPTED), and is the stream still alive (``stale``).

The rules, in the order they apply to a frame whose length and CRC were fine:

* **Late**: a frame arriving more than ``late_factor`` periods after the previous one is
  counted as late (it is still used; staleness is what revokes trust, not lateness).
* **Stuck counter**: the same counter twice in a row means the sender repeats an old frame
  (a frozen task behind a still-running transmit buffer); the frame is rejected.
* **Skip**: a step of 2 to ``1 + max_lost_frames`` means frames were lost on the way;
  the frame is used and the loss counted.
* **Jump** (any other step, backwards included): the sender restarted, or too much was
  lost to tell. The frame is rejected and the monitor *resyncs*: it accepts again after
  ``resync_frames`` consecutive frames in sequence (+1 each), the last of which is the
  first one used. A restarted peer therefore costs ``resync_frames - 1`` periods, never
  a latched fault. The first frame ever seen starts in the same resync state, so a new
  link and a restarted peer follow one rule.
* **Error budget** (after panda's ``wrong_counters``): every CRC/length/range failure,
  stuck counter, skip or jump adds one, up to ``error_budget_limit``; every frame in
  sequence takes one away. Reaching the limit makes the stream UNTRUSTED until the budget
  is back to zero (hysteresis): a link that fails more often than it works is treated as
  no link at all, and earns trust back only with ``error_budget_limit`` good frames.
* **Staleness**: stale when no frame has been accepted for more than ``max_age_s``
  (never accepted = stale). At exactly ``max_age_s`` the stream is still fresh: the
  config's limits read "older than this is a fault".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import StrEnum


class RxVerdict(StrEnum):
    ACCEPTED = "accepted"
    STUCK = "stuck"
    RESYNCING = "resyncing"
    UNTRUSTED = "untrusted"


@dataclass(frozen=True)
class MonitorParams:
    period_s: float
    max_age_s: float
    late_factor: float = 1.5
    max_lost_frames: int = 2
    resync_frames: int = 3
    error_budget_limit: int = 5
    counter_modulo: int = 16

    def __post_init__(self) -> None:
        if not (self.period_s > 0 and self.max_age_s > 0 and self.late_factor >= 1):
            raise ValueError("need period_s > 0, max_age_s > 0 and late_factor >= 1")
        if not 0 <= self.max_lost_frames < self.counter_modulo - 2:
            raise ValueError("max_lost_frames must leave room to tell a jump from a skip")
        if self.resync_frames < 1 or self.error_budget_limit < 1 or self.counter_modulo < 4:
            raise ValueError("need resync_frames >= 1, error_budget_limit >= 1, modulo >= 4")


@dataclass(frozen=True)
class MonitorCounts:
    frames: int = 0  # frames with a valid length and CRC
    accepted: int = 0
    invalid: int = 0  # CRC, length or range failures
    stuck: int = 0
    skips: int = 0  # episodes of lost frames (each a step of 2 .. 1 + max_lost_frames)
    lost_frames: int = 0
    jumps: int = 0  # counter discontinuities that forced a resync
    resyncs: int = 0  # completed resyncs after having been in sync (restarted peers)
    late: int = 0
    untrusted: int = 0  # frames rejected because the error budget was exhausted

    @property
    def counter_errors(self) -> int:
        return self.stuck + self.skips + self.jumps


class ReceiveMonitor:
    def __init__(self, params: MonitorParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self.counts = MonitorCounts()
        self.error_budget = 0
        self.trusted = True
        self.synced = False
        self._ever_synced = False
        self._in_row = 0
        self._last_counter: int | None = None
        self._last_rx_s: float | None = None
        self.last_accepted_s: float | None = None

    def _error(self) -> None:
        self.error_budget = min(self.error_budget + 1, self.params.error_budget_limit)
        if self.error_budget >= self.params.error_budget_limit:
            self.trusted = False

    def record_invalid(self, now_s: float) -> None:
        """A frame of this identifier failed its length, CRC or range check."""
        self.counts = replace(self.counts, invalid=self.counts.invalid + 1)
        self._error()

    def update(self, now_s: float, counter: int) -> RxVerdict:
        """A frame with a valid length and CRC arrived at ``now_s``: may it be used?"""
        p = self.params
        if not 0 <= counter < p.counter_modulo:
            raise ValueError(f"counter {counter} outside 0..{p.counter_modulo - 1}")
        c = replace(self.counts, frames=self.counts.frames + 1)
        if self._last_rx_s is not None and now_s - self._last_rx_s > p.late_factor * p.period_s:
            c = replace(c, late=c.late + 1)
        self._last_rx_s = now_s
        last, self._last_counter = self._last_counter, counter
        step = None if last is None else (counter - last) % p.counter_modulo
        verdict: RxVerdict | None = None
        if step == 0:
            c = replace(c, stuck=c.stuck + 1)
            self._error()
            verdict = RxVerdict.STUCK
        elif step == 1:
            self.error_budget = max(self.error_budget - 1, 0)
            self.trusted = self.trusted or self.error_budget == 0
            self._in_row += 1
        elif step is not None and self.synced and step <= 1 + p.max_lost_frames:
            c = replace(c, skips=c.skips + 1, lost_frames=c.lost_frames + step - 1)
            self._error()
        else:  # first frame, a jump, or any break while resyncing
            if step is not None:
                c = replace(c, jumps=c.jumps + 1)
                self._error()
            self.synced = False
            self._in_row = 1
        if verdict is None and not self.synced:
            if self._in_row >= p.resync_frames:
                self.synced = True
                if self._ever_synced:
                    c = replace(c, resyncs=c.resyncs + 1)
                self._ever_synced = True
            else:
                verdict = RxVerdict.RESYNCING
        if verdict is None and not self.trusted:
            c = replace(c, untrusted=c.untrusted + 1)
            verdict = RxVerdict.UNTRUSTED
        if verdict is None:
            c = replace(c, accepted=c.accepted + 1)
            self.last_accepted_s = now_s
            verdict = RxVerdict.ACCEPTED
        self.counts = c
        return verdict

    def stale_deadline_s(self) -> float:
        """The time after which the stream is stale (-inf if nothing was ever accepted)."""
        if self.last_accepted_s is None:
            return -math.inf
        return self.last_accepted_s + self.params.max_age_s

    def stale(self, now_s: float) -> bool:
        return now_s > self.stale_deadline_s()

    def age_s(self, now_s: float) -> float:
        return math.inf if self.last_accepted_s is None else now_s - self.last_accepted_s
