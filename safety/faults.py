"""Fault monitor: turns the conditions the rules report each cycle into raise/clear events.

The rules return levels ("the steering is off track now"); the operator and the log need
edges ("the steering went off track at 12.34 s", "it recovered at 13.00 s"). Every fault
is raised once when its key appears and cleared once when it disappears, so each is
logged once, not every cycle it stays active. The keys are the mode machine's fault
reasons: a raised record is one ``FaultRaised(reason=key)``, a cleared one is one
``FaultCleared(reason=key)``, the two events of the mode machine this module defines
(``appliance.modes`` takes them from here, so safety needs nothing from the runtime).
Latching is the mode machine's job: ERROR is left only through the operator's
manual-override press once every fault is cleared.

Pure: no clock, no logging (the caller logs the changes), time comes in as ``now_s``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType

HISTORY_LENGTH = 100


@dataclass(frozen=True)
class FaultRaised:
    """A fault key appeared: the mode machine revokes control and latches ERROR."""

    reason: str


@dataclass(frozen=True)
class FaultCleared:
    """A fault key went away: ERROR may be left, but only by the operator's override press."""

    reason: str


@dataclass(frozen=True)
class FaultRecord:
    """One occurrence of a fault; ``cleared_s`` is None while it is still active.

    ``detail`` is the text given when the fault was raised: like the mode machine's
    first timestamp, it says how the trouble began.
    """

    key: str
    detail: str
    raised_s: float
    cleared_s: float | None = None


@dataclass(frozen=True)
class FaultChanges:
    """What changed in one update: raised in the order of ``active``, cleared in raise order."""

    raised: tuple[FaultRecord, ...] = ()
    cleared: tuple[FaultRecord, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.raised or self.cleared)

    def mode_events(self) -> tuple[FaultRaised | FaultCleared, ...]:
        """The mode machine's events, one per record; raises first (they stop motion)."""
        return (
            *(FaultRaised(reason=r.key) for r in self.raised),
            *(FaultCleared(reason=r.key) for r in self.cleared),
        )


class FaultMonitor:
    """Raises each active key once and clears it once when it is no longer active.

    ``active`` maps a stable key ("stale:board.steering", "steering_tracking", ...) to a
    detail text. A detail that changes while its key stays active is the same fault, not
    a new one. ``active_faults`` holds the current faults with the time each was raised;
    ``history`` the last ``HISTORY_LENGTH`` occurrences in the order they were raised,
    the cleared ones with their ``cleared_s``.

    A non-finite ``now_s`` cannot timestamp anything: it is a broken clock, a caller's
    bug, and raises ValueError with the state unchanged (the supervisor's safe stop, not
    a silent "no change", is the answer to a broken clock).
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget everything, as after a restart: faults still active are raised again."""
        self._active: dict[str, FaultRecord] = {}
        self._history: deque[FaultRecord] = deque(maxlen=HISTORY_LENGTH)

    @property
    def active_faults(self) -> Mapping[str, FaultRecord]:
        return MappingProxyType(self._active)

    @property
    def history(self) -> tuple[FaultRecord, ...]:
        return tuple(self._history)

    def update(self, active: Mapping[str, str], now_s: float) -> FaultChanges:
        """Compare this cycle's active faults with the last cycle's; return the changes."""
        if not math.isfinite(now_s):
            raise ValueError(f"now_s must be finite (got {now_s!r})")
        raised = tuple(
            FaultRecord(key, detail, now_s)
            for key, detail in active.items()
            if key not in self._active
        )
        cleared = tuple(
            replace(record, cleared_s=now_s)
            for key, record in self._active.items()
            if key not in active
        )
        for record in cleared:
            del self._active[record.key]
            self._close_in_history(record)
        for record in raised:
            self._active[record.key] = record
            self._history.append(record)
        return FaultChanges(raised, cleared)

    def _close_in_history(self, cleared: FaultRecord) -> None:
        for index in range(len(self._history) - 1, -1, -1):
            if self._history[index].key == cleared.key and self._history[index].cleared_s is None:
                self._history[index] = cleared
                return
        # Older than the last HISTORY_LENGTH occurrences: already out of the history.
