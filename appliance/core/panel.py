"""Operator panel telemetry to button events.

A quick press can start and end between two telemetry frames, so a press is detected by
its counter (the board counts every press, mod 256), not by the button being seen down.
The first frame after a (re)connection, or after a gap in telemetry, only sets the
baseline: counters that changed while we were not looking are old presses, and acting on
them would engage the vehicle on a press nobody made *now* (after any restart, nothing
engages by itself). Held buttons (hold-to-move, the e-stop mushroom) are read from
``buttons_down``.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.actuators.messages import BUTTON_ORDER, Buttons, PanelTelemetry

# More presses than this between two frames (20 ms apart) cannot be a person: a corrupted
# or reset counter. The presses are dropped rather than acted on (deny by default).
MAX_PRESSES_PER_FRAME = 3


@dataclass(frozen=True)
class PanelEvents:
    presses: tuple[Buttons, ...]  # in BUTTON_ORDER, a button once per press counted
    down: Buttons
    implausible: tuple[Buttons, ...] = ()  # counters that jumped too far: ignored


NO_EVENTS = PanelEvents((), Buttons.NONE)


class PanelDecoder:
    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._counts: tuple[int, ...] | None = None
        self._seq: int | None = None

    def update(self, telemetry: PanelTelemetry | None, seq: int | None) -> PanelEvents:
        """Events since the previous frame; ``seq`` is the topic's sample number.

        ``None`` telemetry (stale or never received) forgets the baseline, so the next
        fresh frame starts a new one instead of replaying what happened during the gap.
        """
        if telemetry is None or seq is None:
            self.reset()
            return NO_EVENTS
        if seq == self._seq:
            return PanelEvents((), telemetry.buttons_down)
        previous, self._counts, self._seq = self._counts, tuple(telemetry.press_counts), seq
        if previous is None:
            return PanelEvents((), telemetry.buttons_down)
        presses: list[Buttons] = []
        implausible: list[Buttons] = []
        for button, before, now in zip(BUTTON_ORDER, previous, self._counts, strict=True):
            delta = (now - before) % 256
            if delta == 0:
                continue
            if delta > MAX_PRESSES_PER_FRAME:
                implausible.append(button)
            else:
                presses.extend([button] * delta)  # two quick - presses are two steps
        return PanelEvents(tuple(presses), telemetry.buttons_down, tuple(implausible))
