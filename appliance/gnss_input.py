"""The GNSS/INS receiver as a daemon input: serial client, epoch assembler, ``gnss.pose`` topic.

`GnssClient` (drivers) hands over every NMEA sentence with its receive time; the
`GnssPoseAssembler` (localization) turns each receiver epoch into one `GnssPose` or
`GnssNoFix` in the local east-north frame around ``positioning.origin``; this module owns
the two and publishes each result on the ``gnss.pose`` topic, stamped with its *measurement*
time, so the topic's age is how old the fix is, not when it happened to arrive.

An epoch that lacks one of its sentences is only emitted once its window has passed, so
the service runs a small timer beside the client that calls ``expire`` every
`EXPIRE_PERIOD_S` (half the window): a missing line costs at most 1.5 windows of delay and
never depends on the next epoch arriving.

Without ``positioning.origin`` there is no frame to convert into: the receiver is still
read and counted (a flat-bed that logs its track, a technician checking the cable), but
nothing is published, and the link line says why. Whether a fix is good enough to steer
by is not decided here: the route source judges quality, sigma and age.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from typing import Any, Final

from appliance.config.models import GeodeticOrigin, GnssEndpoint
from appliance.localization.gnss_pose import (
    GnssNoFix,
    GnssPose,
    GnssPoseAssembler,
    GnssPoseParams,
)
from appliance.localization.local_frame import LocalFrame
from appliance.logs import get_logger
from drivers.gnss.client import GnssClient
from drivers.gnss.sentences import NmeaEvent
from drivers.topics import Topic

log = get_logger("gnss_input")

GNSS_POSE_TOPIC: Final = "gnss.pose"
EXPIRE_PERIOD_S: Final = GnssPoseParams(receiver_latency_s=0.0).epoch_window_s / 2.0
NO_ORIGIN: Final = "positioning.origin is not set: fixes are not converted"

GnssOutput = GnssPose | GnssNoFix


class GnssInputError(RuntimeError):
    """The sentence handler failed: the service ends so the supervisor restarts it afresh."""


class RateMeter:
    """Events per second over windows of at least ``window_s`` (0 after a silent window)."""

    def __init__(self, window_s: float = 1.0) -> None:
        self.window_s = window_s
        self.reset(-math.inf)

    def reset(self, now_s: float) -> None:
        self._start_s = now_s
        self._count = 0
        self.per_s = 0.0

    def count(self) -> None:
        self._count += 1

    def update(self, now_s: float) -> float:
        elapsed_s = now_s - self._start_s
        if not math.isfinite(elapsed_s):
            self._start_s, self._count = now_s, 0
        elif elapsed_s >= self.window_s:
            self.per_s = self._count / elapsed_s
            self._start_s, self._count = now_s, 0
        return self.per_s


class GnssInput:
    """One receiver: ``run(beat)`` is the supervised ``gnss`` service, ``topic`` its output."""

    def __init__(
        self,
        endpoint: GnssEndpoint,
        origin: GeodeticOrigin | None,
        port_path: str,
        *,
        max_age_s: float,
        backoff_cap_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``port_path`` is the tty to open (``sim://gnss`` already resolved to the twin's);
        ``max_age_s``: the client calls its stream stale past this age; ``backoff_cap_s``
        the longest wait between attempts to open the port."""
        self.topic: Topic[GnssOutput] = Topic(GNSS_POSE_TOPIC)
        self.assembler: GnssPoseAssembler | None = None
        self.problem = NO_ORIGIN
        if origin is not None:
            frame = LocalFrame(origin.lat_deg, origin.lon_deg, origin.alt_m)
            params = GnssPoseParams(receiver_latency_s=endpoint.receiver_latency_s)
            self.assembler = GnssPoseAssembler(frame, params)
            self.problem = ""
        self.client = GnssClient(
            port_path,
            self._on_event,
            baudrate_bps=endpoint.baudrate_bps,
            max_age_s=max_age_s,
            # Like the boards: whether the receiver is there is the fix's age, judged by
            # whoever steers by it; the heartbeat only says this software is alive.
            beat_while_reconnecting=True,
            backoff_cap_s=backoff_cap_s,
            clock=clock,
        )
        self.fixes = RateMeter()
        self._clock = clock
        self._failure: BaseException | None = None

    async def run(self, beat: Callable[[], None]) -> None:
        """Read, assemble, publish and expire until cancelled; a restart begins afresh."""
        self._failure = None
        self.fixes.reset(self._clock())
        if self.assembler is not None:
            self.assembler.reset()
        else:
            log.warning("gnss_not_converted", reason=NO_ORIGIN)
        async with asyncio.TaskGroup() as group:
            group.create_task(self.client.run(beat))
            group.create_task(self._expire_loop())

    async def _expire_loop(self) -> None:
        while True:
            now_s = self._clock()
            if self._failure is not None:
                failure = self._failure
                raise GnssInputError(f"{type(failure).__name__}: {failure}") from failure
            if self.assembler is not None:
                self._publish(self.assembler.expire(now_s))
            self.fixes.update(now_s)
            await asyncio.sleep(EXPIRE_PERIOD_S)

    def _on_event(self, event: NmeaEvent, receive_time_s: float) -> None:
        """The client's reader callback: it must not raise into the event loop (which
        would log and carry on), so a failure is kept for the service to end on."""
        if self.assembler is None or self._failure is not None:
            return
        try:
            self._publish(self.assembler.update(event, receive_time_s))
        except Exception as exc:
            self._failure = exc

    def _publish(self, output: GnssOutput | None) -> None:
        if output is None:
            return
        if isinstance(output, GnssPose):
            self.fixes.count()
        self.topic.publish(output, output.measurement_time_s)

    def link_line(self, now_s: float | None = None) -> str:
        """One line for ``dbw status`` and the heartbeat log: ``up ...`` or ``down: why``."""
        now = self._clock() if now_s is None else now_s
        health = self.client.health(now)
        if not health.connected:
            return f"down: {health.last_error or 'not open yet'}"
        if health.stale:
            age_s = health.last_event_age_s
            silent = f"{age_s:.1f} s" if math.isfinite(age_s) else "ever since it opened"
            return f"down: no sentence for {silent} (port open)"
        rejects = f"rejects {health.error_count}"
        if self.assembler is None:
            return f"up {health.events_per_s:.1f} sentences/s, {rejects}; {self.problem}"
        sample = self.topic.latest()
        head = f"up {self.fixes.per_s:.1f} fixes/s"
        if sample is None:
            return f"{head}, no epoch yet, {rejects}"
        pose = sample.value
        if isinstance(pose, GnssNoFix):
            return f"{head}, no fix: {pose.reason}, {rejects}"
        sigma = "sigma ?" if pose.sigma_worst_m is None else f"sigma {pose.sigma_worst_m:.2f} m"
        sats = "? sats" if pose.satellites is None else f"{pose.satellites} sats"
        return f"{head}, quality {pose.quality.name}, {sigma}, {sats}, {rejects}"

    def status(self, now_s: float | None = None) -> dict[str, Any] | None:
        """The latest epoch for ``dbw status`` and ``dbw route record``: where the antenna
        is in the local frame, its quality and age; None before the first epoch."""
        now = self._clock() if now_s is None else now_s
        sample = self.topic.latest()
        if sample is None:
            return None
        pose = sample.value
        age_s = now - pose.measurement_time_s
        base: dict[str, Any] = {
            "measurement_time_s": pose.measurement_time_s,
            "age_s": round(age_s, 4) if math.isfinite(age_s) else None,
        }
        if isinstance(pose, GnssNoFix):
            return base | {"fix": False, "reason": pose.reason}
        return base | {
            "fix": True,
            "east_m": round(pose.east_m, 4),
            "north_m": round(pose.north_m, 4),
            "yaw_deg": None if pose.yaw_rad is None else round(math.degrees(pose.yaw_rad), 3),
            "speed_mps": pose.speed_mps,
            "quality": pose.quality.name,
            "sigma_m": pose.sigma_worst_m,
            "satellites": pose.satellites,
        }
