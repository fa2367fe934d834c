"""Staleness: every input has an age limit; a stale critical input revokes control.

A command computed from an old scan or an old steering pot reading is a command for a
vehicle that is no longer where the controller thinks it is. The guard is deny by
default: an input that is missing from the ages it is given (never received, or its
producer died and was dropped) or whose age is not a finite, non-negative number counts
as stale. A negative age means a timestamp from the future, i.e. a broken clock, and is
trusted no more than a missing one.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from types import MappingProxyType

# Everything the vehicle needs to move safely under automatic control. The pose is
# left out because until guidance exists nothing consumes it; a guidance issue adds it.
DEFAULT_CRITICAL_INPUTS: tuple[str, ...] = (
    "scan.left",
    "scan.right",
    "pc104.status",
    "steering.pot",
    "board.steering",
    "board.throttle",
    "board.brake",
    "board.panel",
)


class StalenessGuard:
    """Names every stale critical input, every cycle, and remembers since when.

    Which inputs are critical is a constructor argument, and every critical input must
    have an age limit: a critical input the guard cannot judge is a configuration error
    raised at start-up, not a silent pass at run time.
    """

    def __init__(self, age_limits_s: Mapping[str, float], critical: Iterable[str]) -> None:
        self.critical: tuple[str, ...] = tuple(dict.fromkeys(critical))
        unknown = [name for name in self.critical if name not in age_limits_s]
        if unknown:
            raise ValueError(f"critical inputs without an age limit: {unknown}")
        bad = [
            name for name, limit in age_limits_s.items() if not (limit > 0 and math.isfinite(limit))
        ]
        if bad:
            raise ValueError(f"age limits must be positive and finite: {bad}")
        self.age_limits_s: Mapping[str, float] = MappingProxyType(dict(age_limits_s))
        self.reset()

    def reset(self) -> None:
        self.stale_since_s: dict[str, float] = {}

    def is_stale(self, name: str, ages_s: Mapping[str, float]) -> bool:
        """Stale unless the age is known, finite, non-negative and within its limit."""
        age_s = ages_s.get(name)
        limit_s = self.age_limits_s.get(name)
        if age_s is None or limit_s is None:
            return True
        return not (math.isfinite(age_s) and 0.0 <= age_s <= limit_s)

    def update(self, ages_s: Mapping[str, float], now_s: float) -> tuple[str, ...]:
        """Return the stale critical inputs, in the order they were declared critical.

        ``now_s`` only timestamps when each input went stale (for the fault log); the
        verdict itself depends on the ages alone, so it is decided within this cycle.
        """
        stale = tuple(name for name in self.critical if self.is_stale(name, ages_s))
        self.stale_since_s = {name: self.stale_since_s.get(name, now_s) for name in stale}
        return stale
