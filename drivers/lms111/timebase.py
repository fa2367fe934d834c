"""Unwrapping the scanner's 32-bit microsecond clock.

Every scan carries "time since start-up" as a uint32 in µs: it wraps every 2**32 µs
(71.6 min), and it restarts from 0 when the scanner reboots. A consumer that wants a
monotonic device time needs to tell the two apart, which the raw value alone cannot always do:

* a step forwards (``raw >= previous``) is time passing, however large (a reconnect);
* a step backwards is a **wrap** only if the modular step ``raw + 2**32 - previous`` is at
  most ``max_gap_us`` (default 60 s): the counter must have been just below 2**32 and be just
  above 0. When host receive times are given for both samples, the modular step must also not
  exceed the host time that passed (plus ``host_tolerance_s``): a clock cannot advance more
  than real time did;
* any other step backwards is a **reboot**: a new epoch starts and the unwrapped time restarts
  at the raw value (it jumps back; `epoch` tells the two stretches apart). Inventing
  continuity across a reboot would hide the event from everything downstream.

A reboot that lands within ``max_gap_us`` of a wrap without host times is indistinguishable
from the wrap; passing ``now_s`` removes that case unless the reboot took less than the
tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.lms111.errors import ProtocolError

WRAP_US = 1 << 32


@dataclass(frozen=True)
class UnwrapParams:
    max_gap_us: int = 60_000_000
    host_tolerance_s: float = 1.0


class DeviceTimeUnwrapper:
    """``update(raw_us[, now_s]) -> unwrapped_us``; one instance per scanner."""

    def __init__(self, params: UnwrapParams | None = None) -> None:
        self.params = params or UnwrapParams()
        self.reset()

    def reset(self) -> None:
        self._previous_raw_us: int | None = None
        self._previous_now_s: float | None = None
        self._offset_us = 0
        self.wraps = 0
        self.reboots = 0
        self.epoch = 0

    def update(self, raw_us: int, now_s: float | None = None) -> int:
        if not 0 <= raw_us < WRAP_US:
            raise ProtocolError(f"device time {raw_us} is not a uint32")
        previous = self._previous_raw_us
        if previous is not None and raw_us < previous:
            if self._is_wrap(raw_us + WRAP_US - previous, now_s):
                self._offset_us += WRAP_US
                self.wraps += 1
            else:
                self._offset_us = 0
                self.reboots += 1
                self.epoch += 1
        self._previous_raw_us = raw_us
        self._previous_now_s = now_s
        return self._offset_us + raw_us

    def _is_wrap(self, step_us: int, now_s: float | None) -> bool:
        if step_us > self.params.max_gap_us:
            return False
        if now_s is None or self._previous_now_s is None:
            return True
        elapsed_us = (now_s - self._previous_now_s + self.params.host_tolerance_s) * 1e6
        return step_us <= elapsed_us
