"""The high-level frames the client sends the PC104, and the rules for what goes out.

The latest motion command, pose, expected pose and announced state; which command goes
out at a tick (deny-by-default, :func:`command_to_send`); the poses riding with a command
frame only while younger than the command timeout and no faster than their own period; a
command change that matters going out early; a rolling counter per frame; a frame the
transmit buffer refuses dropped and counted.

Kept apart from :mod:`drivers.pc104.client`, which owns the bus, its deadlines and the
receive side, because these rules are about the frames, not the connection: they hold no
task and no bus, take the time, the link and the PC104's status as arguments, and read the
same whichever link carries them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from structlog.typing import FilteringBoundLogger

from drivers.pc104 import protocol
from drivers.pc104.client_core import ClientParams, command_to_send
from drivers.pc104.link import BusLink, Episode
from drivers.pc104.messages import (
    HighLevelState,
    HlExpectedPose,
    HlHeartbeat,
    HlMessage,
    HlPose,
    MotionCommand,
    Pc104Status,
)

_SENT = (MotionCommand, HlHeartbeat, HlPose, HlExpectedPose)


class HlSender:
    """The latest command, poses and state, and the frames built from them on a link."""

    def __init__(
        self,
        params: ClientParams,
        log: FilteringBoundLogger,
        note_error: Callable[[str], None],
    ) -> None:
        """``note_error`` records why a send failed as the client's last error."""
        self.params = params
        self._note_error = note_error
        self._command: MotionCommand | None = None
        self._command_s = -math.inf
        self.holding = False
        self.state = HighLevelState.STANDBY
        self._pose: HlPose | None = None
        self._expected: HlExpectedPose | None = None
        self._poses_set_s = self._poses_sent_s = -math.inf
        self._counters = {protocol.spec_for(t).frame_id: 0 for t in _SENT}
        self._last_command_sent_s = -math.inf
        self.sent = self.dropped = 0
        self._ep_drops = Episode(log, "pc104_send_drops")
        self._ep_hold = Episode(log, "pc104_holding_stop")

    # ---- what the control loop hands in ----------------------------------------------
    def set_command(self, command: MotionCommand, now_s: float) -> bool:
        """Make ``command`` the latest; raises CommandRefused at once if it is outside the
        DBC, so it never becomes the latest command. Returns whether the change is urgent.

        A change of pattern (STOP above all) or a lower speed goes on the wire now, not at
        the next tick of the periodic sender: a fault, an override or a brake tap must
        reach the PC104 within the control cycle."""
        protocol.encode(command, 0)
        previous = self._command
        self._command = command
        self._command_s = now_s
        return (
            previous is None
            or previous.pattern is not command.pattern
            or abs(command.speed_mps) < abs(previous.speed_mps)
        )

    def command_due(self, urgent: bool, now_s: float) -> bool:
        """Whether a command frame goes out now, before the tick. Other changes than urgent
        ones wait for the tick unless half a period has passed, which phase-locks the frames
        to the control loop without flooding the bus."""
        return urgent or now_s - self._last_command_sent_s >= self.params.command_period_s / 2

    def set_poses(self, pose: HlPose | None, expected: HlExpectedPose | None, now_s: float) -> None:
        """Raises CommandRefused at once for a value outside the DBC."""
        if pose is not None:
            protocol.encode(pose, 0)
        if expected is not None:
            protocol.encode(expected, 0)
        self._pose, self._expected = pose, expected
        self._poses_set_s = now_s

    def set_state(self, state: HighLevelState) -> bool:
        """The state announced in HL_Heartbeat; returns whether it changed."""
        changed = state is not self.state
        self.state = state
        return changed

    # ---- the frames ------------------------------------------------------------------
    def send_command_frame(
        self, link: BusLink, now_s: float, status: Pc104Status | None, status_fresh: bool
    ) -> None:
        command, why, self.holding = command_to_send(
            self._command,
            self._command_s,
            now_s,
            self.params.command_timeout_s,
            status,
            status_fresh,
            self.holding,
        )
        if why and self._command is not None:
            self._ep_hold.occur(now_s, reason=why)
        elif not why:
            self._ep_hold.clear(now_s)
        self._last_command_sent_s = now_s
        self.transmit(link, command, now_s)
        # The poses ride with the command, but at their own period at most: a control loop
        # that sends commands faster (a command frame goes out early on a change) must not
        # make them faster than the DBC's 20 ms.
        if now_s - self._poses_sent_s < 0.75 * self.params.command_period_s:
            return
        if now_s - self._poses_set_s > self.params.command_timeout_s:
            return
        for message in (self._pose, self._expected):
            if message is not None:
                self.transmit(link, message, now_s)
                self._poses_sent_s = now_s

    def send_heartbeat(self, link: BusLink, now_s: float) -> None:
        self.transmit(link, HlHeartbeat(self.state), now_s)

    def transmit(self, link: BusLink, message: HlMessage, now_s: float) -> None:
        frame_id = protocol.spec_for(type(message)).frame_id
        counter = self._counters[frame_id]
        self._counters[frame_id] = (counter + 1) % protocol.COUNTER_MODULO
        arbitration_id, data = protocol.encode(message, counter)
        if link.send(arbitration_id, data):
            self.sent += 1
            self._ep_drops.clear(now_s, total_drops=self.dropped)
        else:
            self.dropped += 1
            self._note_error(f"send dropped: {link.last_send_error}")
            self._ep_drops.occur(now_s, error=str(link.last_send_error))
