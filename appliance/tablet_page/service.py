"""The tablet page in the daemon: the gate, the server, and the hold on a topic.

The server's word on the hold (`TabletActions.hold_changed`) is published on the
``tablet.hold`` topic, which the control loop reads each cycle into the core's inputs
(`ControlInputs.tablet`, recorded with every cycle): the core counts it held until the
last beat's time runs out. A release wakes the loop at once, so the stop goes out within
the cycle, not at the next one's time. What the page draws comes from the daemon's
status and, on a forklift with a `pallet` source, from the source (`state`, `select`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

from appliance.config.forklift_models import TabletPageSettings
from appliance.core.inputs import TABLET_HOLD_TOPIC, TabletHold
from appliance.tablet_page.gate import TabletGate, TabletParams
from appliance.tablet_page.server import TabletPage
from drivers.topics import Topic

TABLET_TOPIC = TABLET_HOLD_TOPIC
NO_SOURCE = "this vehicle has no pallet source to send"

StateSource = Callable[[], dict[str, Any]]
Selector = Callable[[str], tuple[bool, str]]


class TabletService:
    """Builds the gate and the page from the vehicle file; the daemon supervises
    ``page.run`` and shows `status` in `dbw status` (the pairing code among it)."""

    def __init__(
        self,
        settings: TabletPageSettings,
        clock: Callable[[], float],
        wake: Callable[[], None],
        state: StateSource,
        select: Selector | None = None,
        random_bytes: Callable[[int], bytes] = os.urandom,
    ) -> None:
        self.clock = clock
        self._wake = wake
        self._state = state
        self._select = select
        self.topic: Topic[TabletHold] = Topic(TABLET_TOPIC)
        self.gate = TabletGate(random_bytes, TabletParams(hold_timeout_s=settings.hold_timeout_s))
        self.page = TabletPage(
            self.gate,
            self,
            settings.host,
            settings.port,
            host_names=settings.host_names,
            clock=clock,
        )

    # ---- TabletActions -----------------------------------------------------------------
    def hold_changed(self, held: bool, until_s: float) -> None:
        previous = self.topic.latest()
        self.topic.publish(TabletHold(held, until_s), self.clock())
        if not held and previous is not None and previous.value.held:
            self._wake()  # the release goes out now, not at the next cycle's time

    def select(self, pallet: str) -> tuple[bool, str]:
        if self._select is None:
            return False, NO_SOURCE
        return self._select(pallet)

    def state(self) -> dict[str, Any]:
        return self._state()

    def display_note(self) -> str:
        """For the operator panel's display: the code to pair with, while no tablet is
        paired (the code is shown at the vehicle, so pairing needs someone there)."""
        return "" if self.gate.paired else f"PAIR {self.gate.code}"

    # ---- for `dbw status` --------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        now_s = self.clock()
        return {
            "listening": self.page.bound_port is not None,
            "address": f"{self.page.host}:{self.page.bound_port or self.page.port}",
            "paired": self.gate.paired,
            "pairing_code": self.gate.code,
            "held": self.gate.held(now_s),
            "refused_requests": self.gate.refusals,
        }
