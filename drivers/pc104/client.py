"""The asyncio client of the PC104 link: a short loop around the sans-I/O codec.

One task (the supervisor's service ``run``) owns the bus: it sends the motion command at
the control rate and the heartbeat at 10 Hz against absolute deadlines, drains received
frames between deadlines (a bounded number per turn, so a flooded bus cannot delay a
command), checks them with one :class:`ReceiveMonitor` per PC104 message and publishes the
accepted ones to latest-value topics stamped with their receive time. One task rather
than a sender and a receiver: ordering is deterministic and there is nothing to join.

What goes out is deny-by-default: the latest command from :meth:`send_command` only while
it is younger than ``lower_layer_command_timeout_s``, the PC104 status is fresh and the
PC104 reports automatic control; otherwise STOP, and once a motion command has been
replaced by STOP the client holds STOP until the control loop sends STOP itself. The
PC104 applies the same rule on its side (it stops 100 ms after commands stop, then waits
for a STOP), so whether motion resumes is always the control loop's explicit decision.
The pose and the expected pose (:meth:`send_pose`) follow each command frame under the
same age rule, for a PC104 that closes the steering loop itself. Those frames and their
rules are :class:`drivers.pc104.sender.HlSender`'s; this module runs the bus around them.

Failures never end ``run``: a full transmit buffer drops the frame, a lost interface
closes and reopens the bus with backoff, a restarted PC104 is resynchronised by the
monitors; each is logged once when it starts and once when it ends. ``beat`` is called on
every turn of the loop, reconnecting included: a dead cable is a data fault that the
stale status reports to the safety layer, not a hung service a restart would fix.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable

import can
import structlog
from structlog.typing import FilteringBoundLogger

from drivers.pc104 import protocol
from drivers.pc104.client_core import ClientParams, LinkHealth, Pc104Topics, RateMeter
from drivers.pc104.endpoint import BusEndpoint
from drivers.pc104.errorframes import BusCondition, bus_condition
from drivers.pc104.link import BusFactory, BusLink, Episode, LinkLost, bus_factory, next_deadline
from drivers.pc104.messages import (
    PROTOCOL_VERSION,
    HighLevelState,
    HlExpectedPose,
    HlHeartbeat,
    HlPose,
    Inclinometer,
    MotionCommand,
    MotorPulses,
    Pc104Heartbeat,
    Pc104Status,
    WheelAngles,
)
from drivers.pc104.monitor import MonitorParams, ReceiveMonitor, RxVerdict
from drivers.pc104.protocol import ErrorReason, Pc104ProtocolError
from drivers.pc104.sender import HlSender

log: FilteringBoundLogger = structlog.get_logger(component="pc104")

MAX_FRAMES_PER_TURN = 256
_BUS_STATES = {can.BusState.PASSIVE: BusCondition.PASSIVE, can.BusState.ERROR: BusCondition.BUS_OFF}


class Pc104Client:
    """The daemon's end of the PC104 link. ``run(beat)`` is the supervised service."""

    def __init__(
        self,
        params: ClientParams,
        endpoint: BusEndpoint,
        *,
        topics: Pc104Topics | None = None,
        open_bus: BusFactory | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``open_bus`` replaces opening ``endpoint`` (tests hand in their own bus)."""
        self.params = params
        self.topics = topics if topics is not None else Pc104Topics.create()
        self._open_bus = (
            open_bus if open_bus is not None else bus_factory(endpoint, protocol.PC104_IDS)
        )
        self._clock = clock
        # Awaited before a batch of received frames is decoded: the runtime keeps that
        # work out of the moments before a control deadline (appliance.timing.ControlSlot).
        self.before_decode: Callable[[], Awaitable[None]] | None = None
        # Called with every frame received, any sender's, and its receive time (the recorder).
        self.raw_listeners: list[Callable[[can.Message, float], None]] = []
        self.monitors: dict[int, ReceiveMonitor] = {}
        for spec in protocol.SPECS_BY_ID.values():
            if spec.frame_id in protocol.PC104_IDS:
                max_age_s = max(self.params.status_max_age_s, 3 * spec.period_s)
                self.monitors[spec.frame_id] = ReceiveMonitor(
                    MonitorParams(period_s=spec.period_s, max_age_s=max_age_s)
                )
        self._status_id = protocol.spec_for(Pc104Status).frame_id
        self._heartbeat_period_s = protocol.spec_for(HlHeartbeat).period_s
        self._sender = HlSender(self.params, log, self._note_error)
        self._link: BusLink | None = None
        self._send_loss: LinkLost | None = None  # a send for a caller found the link lost
        self._next_command_s = self._next_heartbeat_s = -math.inf
        self._status: Pc104Status | None = None
        self._errors = {reason: 0 for reason in ErrorReason}
        self._received = self._reconnects = 0
        self._in_rate, self._out_rate = RateMeter(), RateMeter()
        self._frame_condition = BusCondition.ACTIVE
        self._polled_condition = BusCondition.ACTIVE
        self._next_poll_s = -math.inf
        self._stale_since_s: float | None = None
        self._last_error = ""
        self._ep_link = Episode(log, "pc104_link_down")
        self._ep_stale = Episode(log, "pc104_status_stale")
        self._ep_bus = Episode(log, "pc104_bus_error_state")
        self._ep_version = Episode(log, "pc104_protocol_mismatch")
        self._ep_rx = {i: Episode(log, "pc104_receive_errors") for i in self.monitors}

    # ---- what the control loop calls --------------------------------------------------
    def send_command(self, command: MotionCommand, now_s: float | None = None) -> None:
        """Make ``command`` the one sent every period; raises CommandRefused at once (in
        the caller) if it is outside the DBC, so it never becomes the latest command. An
        urgent change goes on the wire now (:meth:`HlSender.set_command`)."""
        urgent = self._sender.set_command(command, self._clock() if now_s is None else now_s)
        link = self._link
        if link is None:
            return
        now = self._clock()
        due = self._sender.command_due(urgent, now)
        if due and self._send_for_caller(lambda: self._send_command_frame(link, now)):
            self._next_command_s = now + self.params.command_period_s

    def send_pose(
        self, pose: HlPose | None, expected: HlExpectedPose | None, now_s: float | None = None
    ) -> None:
        """The pose and the expected pose sent after each motion command (None: none).

        Each goes out only while it is younger than ``lower_layer_command_timeout_s``, like
        the command: a control loop that stops calling stops them too, and a PC104 that
        closes the loop on pose then stops the vehicle. Raises CommandRefused at once for
        a value outside the DBC."""
        self._sender.set_poses(pose, expected, self._clock() if now_s is None else now_s)

    def set_state(self, state: HighLevelState) -> None:
        """The high-level state announced in HL_Heartbeat; a change is sent at once."""
        changed = self._sender.set_state(state)
        link = self._link
        if changed and link is not None:
            now = self._clock()
            if self._send_for_caller(lambda: self._sender.send_heartbeat(link, now)):
                self._next_heartbeat_s = now + self._heartbeat_period_s

    def _send_for_caller(self, send: Callable[[], None]) -> bool:
        """Send now on behalf of a caller (the control cycle): a lost link is this client's
        to handle, never the caller's. It is kept for the serve loop, which closes the bus
        and reopens it; the caller's cycle goes on, and the PC104's inputs going stale
        make the fault. (Seen: a USB-CAN adapter gone, EIO on write, crashed the control
        service instead of faulting the core.)"""
        try:
            send()
        except LinkLost as exc:
            if self._send_loss is None:
                self._send_loss = exc
            return False
        return True

    def health(self, now_s: float | None = None) -> LinkHealth:
        live = now_s is None
        now_s = self._clock() if now_s is None else now_s
        status_monitor = self.monitors[self._status_id]
        monitors = self.monitors.values()
        status = self._status
        # A caller may look between the stale deadline and the loop's wake-up for it:
        # then the report is consistent (stale, and since when) and the episode logged now.
        # A look at another time (``now_s`` given) only reads.
        stale = self._update_stale(now_s) if live else status_monitor.stale(now_s)
        return LinkHealth(
            connected=self._link is not None,
            stale=stale,
            status_age_s=status_monitor.age_s(now_s),
            frames_in_per_s=self._in_rate.rate_per_s,
            frames_out_per_s=self._out_rate.rate_per_s,
            frames_received=self._received,
            crc_errors=self._errors[ErrorReason.CRC],
            malformed_frames=self._errors[ErrorReason.LENGTH] + self._errors[ErrorReason.RANGE],
            counter_errors=sum(m.counts.counter_errors for m in monitors),
            late_frames=sum(m.counts.late for m in monitors),
            send_drops=self._sender.dropped,
            resyncs=sum(m.counts.resyncs for m in monitors),
            reconnects=self._reconnects,
            bus_condition=max(self._frame_condition, self._polled_condition),
            control_source=None if status is None else status.control_source,
            peer_ready=status is not None and status.ready and not status_monitor.stale(now_s),
            holding_stop=self._sender.holding,
            stale_since_s=self._stale_since_s,
            last_error=self._last_error,
        )

    # ---- the service ------------------------------------------------------------------
    async def run(self, beat: Callable[[], None]) -> None:
        """Run the link until cancelled; never returns and never raises for link faults."""
        backoff_s = self.params.reopen_initial_backoff_s
        first = True
        log.info("pc104_client_started", dbc=protocol.DATABASE.version)
        try:
            while True:
                if not first:
                    await self._pause(backoff_s, beat)
                    backoff_s = min(
                        backoff_s * self.params.reopen_backoff_factor,
                        self.params.reopen_backoff_cap_s,
                    )
                first = False
                try:
                    link = BusLink(self._open_bus())
                except (can.CanError, OSError, ValueError) as exc:
                    self._lost(f"cannot open the bus: {exc}")
                    continue
                self._link = link
                self._send_loss = None  # whatever the old link did is over
                accepted_before = self.monitors[self._status_id].counts.accepted
                try:
                    await self._serve(link, beat)
                except LinkLost as exc:
                    self._lost(str(exc))
                except BaseException:  # cancelled: close (joining python-can's thread), re-raise
                    self._link = None
                    await link.aclose()
                    raise
                self._link = None
                self._reconnects += 1
                if self.monitors[self._status_id].counts.accepted > accepted_before:
                    backoff_s = self.params.reopen_initial_backoff_s  # this session worked
                await link.aclose()
        finally:
            log.info("pc104_client_stopped")

    async def _pause(self, duration_s: float, beat: Callable[[], None]) -> None:
        end_s = self._clock() + duration_s
        while (left_s := end_s - self._clock()) > 0:
            beat()
            await asyncio.sleep(min(left_s, self.params.command_period_s))

    def _lost(self, why: str) -> None:
        self._last_error = why
        self._ep_link.occur(self._clock(), error=why)

    async def _serve(self, link: BusLink, beat: Callable[[], None]) -> None:
        now_s = self._clock()
        self._next_command_s = self._next_heartbeat_s = now_s
        while True:
            link.check()
            if self._send_loss is not None:
                loss, self._send_loss = self._send_loss, None
                raise loss
            now_s = self._clock()
            if now_s >= self._next_command_s:
                self._send_command_frame(link, now_s)
                self._next_command_s = next_deadline(
                    self._next_command_s, self.params.command_period_s, now_s
                )
            if now_s >= self._next_heartbeat_s:
                self._sender.send_heartbeat(link, now_s)
                self._next_heartbeat_s = next_deadline(
                    self._next_heartbeat_s, self._heartbeat_period_s, now_s
                )
            self._watch(link, now_s)
            beat()
            wake_s = min(self._next_command_s, self._next_heartbeat_s)
            status_monitor = self.monitors[self._status_id]
            if not status_monitor.stale(now_s):
                wake_s = min(wake_s, status_monitor.stale_deadline_s() + 1e-4)
            message = await link.next_message(wake_s - self._clock())
            arrived_s: float | None = None
            if message is not None and self.before_decode is not None:
                arrived_s = self._clock()  # what waits is the decoding, not the stamp
                await self.before_decode()
            handled = 0
            while message is not None:
                self._on_message(message, self._clock() if arrived_s is None else arrived_s)
                handled += 1
                message = link.poll() if handled < MAX_FRAMES_PER_TURN else None

    # ---- sending (the frames and their rules: drivers.pc104.sender) -----------------
    def _send_command_frame(self, link: BusLink, now_s: float) -> None:
        status_fresh = not self.monitors[self._status_id].stale(now_s)
        self._sender.send_command_frame(link, now_s, self._status, status_fresh)

    def _note_error(self, why: str) -> None:
        self._last_error = why

    # ---- receiving --------------------------------------------------------------------
    def _on_message(self, message: can.Message, now_s: float) -> None:
        self._received += 1
        for listener in self.raw_listeners:
            listener(message, now_s)
        if message.is_error_frame:
            condition = bus_condition(message.arbitration_id, bytes(message.data))
            if condition is not None:
                self._set_frame_condition(condition, now_s)
            return
        monitor = self.monitors.get(message.arbitration_id)
        if monitor is None or message.is_extended_id or message.is_remote_frame:
            return  # another node's traffic
        try:
            frame = protocol.decode(message.arbitration_id, message.data, now_s)
        except Pc104ProtocolError as exc:
            self._errors[exc.reason] += 1
            monitor.record_invalid(now_s)
            self._last_error = str(exc)
            self._ep_rx[message.arbitration_id].occur(now_s, reason=exc.reason, error=str(exc))
            return
        verdict = monitor.update(now_s, frame.counter)
        episode = self._ep_rx[message.arbitration_id]
        if verdict is RxVerdict.ACCEPTED:
            if monitor.error_budget == 0:
                episode.clear(now_s, message=protocol.SPECS_BY_ID[frame.arbitration_id].name)
            self._publish(frame)
        elif verdict is not RxVerdict.RESYNCING or monitor.counts.jumps:
            name = protocol.SPECS_BY_ID[frame.arbitration_id].name
            episode.occur(now_s, reason=verdict, message=name, counter=frame.counter)

    def _publish(self, frame: protocol.DecodedFrame) -> None:
        message, stamp_s = frame.message, frame.received_s
        if isinstance(message, Pc104Status):
            self._status = message
            self.topics.status.publish(message, stamp_s)
            if self._frame_condition is BusCondition.BUS_OFF:  # traffic proves we are back
                self._set_frame_condition(BusCondition.ACTIVE, stamp_s)
            self._ep_link.clear(stamp_s, reconnects=self._reconnects)
        elif isinstance(message, WheelAngles):
            self.topics.wheel_angles.publish(message, stamp_s)
        elif isinstance(message, MotorPulses):
            self.topics.motor_pulses.publish(message, stamp_s)
        elif isinstance(message, Inclinometer):
            self.topics.inclinometer.publish(message, stamp_s)
        elif isinstance(message, Pc104Heartbeat):
            if message.protocol_version != PROTOCOL_VERSION:
                self._last_error = (
                    f"PC104 speaks protocol {message.protocol_version}, we {PROTOCOL_VERSION}"
                )
                self._ep_version.occur(stamp_s, error=self._last_error)
            self.topics.heartbeat.publish(message, stamp_s)

    def _set_frame_condition(self, condition: BusCondition, now_s: float) -> None:
        self._frame_condition = condition
        if condition is BusCondition.ACTIVE:
            self._ep_bus.clear(now_s)
        elif condition >= BusCondition.PASSIVE:
            self._last_error = f"CAN controller {condition.name}"
            self._ep_bus.occur(now_s, condition=condition.name)

    # ---- bookkeeping ------------------------------------------------------------------
    def _update_stale(self, now_s: float) -> bool:
        """Note (and log once) when the status went stale; whoever looks first notices."""
        stale = self.monitors[self._status_id].stale(now_s)
        if stale and self._stale_since_s is None:
            self._stale_since_s = now_s
            if self.monitors[self._status_id].last_accepted_s is not None:
                self._ep_stale.occur(now_s, max_age_s=self.params.status_max_age_s)
        elif not stale and self._stale_since_s is not None:
            self._stale_since_s = None
            self._ep_stale.clear(now_s)
        return stale

    def _watch(self, link: BusLink, now_s: float) -> None:
        self._update_stale(now_s)
        self._in_rate.update(now_s, self._received)
        self._out_rate.update(now_s, self._sender.sent)
        if now_s >= self._next_poll_s:
            self._next_poll_s = now_s + self.params.bus_state_poll_s
            try:
                state = link.bus.state
            except (can.CanError, NotImplementedError, OSError):
                state = can.BusState.ACTIVE
            self._polled_condition = _BUS_STATES.get(state, BusCondition.ACTIVE)
