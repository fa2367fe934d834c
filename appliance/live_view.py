"""The live view: what the vehicle sees and does, to Foxglove over its WebSocket protocol.

Off by default, and on 127.0.0.1 unless the vehicle file says otherwise. The server is
the maintained ``foxglove-sdk``'s: it runs on threads of its own (Rust), so the event
loop only hands it messages, and only when someone is watching (``has_sinks``) and no
faster than ``max_rate_hz`` per topic, so its cost on the loop is bounded whether one
browser watches or none. The messages are Foxglove's well-known schemas, so its 3D,
Log and Raw Messages panels show them with no plug-in:

- ``/scan/left``, ``/scan/right``: ``foxglove.LaserScan`` in the vehicle frame;
- ``/dbw/pose``: ``foxglove.PoseInFrame``, the pose the PC104 is given (docking), and
  ``/tf``: ``foxglove.FrameTransform`` launcher -> vehicle, so the scans sit on the map;
- ``/dbw/gnss_pose``: ``foxglove.PoseInFrame``, the GNSS/INS epoch in the ``enu`` frame,
  and ``/dbw/route``: ``foxglove.SceneUpdate``, the selected route's points near the
  vehicle as a line in the same frame (once a second: it changes as the vehicle drives);
- ``/dbw/status``: JSON: mode, set speed, commands, engage blockers, faults, the wish;
- ``/log``: ``foxglove.Log``, every note of the core (mode changes, faults) at once.
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import math
from collections.abc import Callable, Mapping
from typing import Any

import foxglove
from foxglove import Channel, Context
from foxglove.channels import (
    FrameTransformChannel,
    LaserScanChannel,
    LogChannel,
    PoseInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.messages import (
    Color,
    FrameTransform,
    LaserScan,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    Point3,
    Pose,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    Timestamp,
    Vector3,
)

from appliance.config import VehicleConfig
from appliance.core.inputs import ControlInputs
from appliance.core.output import CoreOutput, describe_commands
from appliance.localization.gnss_pose import GnssPose
from appliance.logs import get_logger
from appliance.supervisor import ServiceContext
from appliance.topics import TopicRegistry
from drivers.lms111.mounted import MountedScan
from drivers.topics import Sample

log = get_logger("live_view")

BEAT_S = 1.0
ROUTE_RATE_HZ = 1.0  # the route near the vehicle changes only as the vehicle drives
_LEVELS = {"fault_raised": LogLevel.Error, "fault_cleared": LogLevel.Info}
STATUS_SCHEMA = {
    "title": "dbw.status",
    "type": "object",
    "description": "The control core's state each published cycle",
}


def check_host(host: str, allow_non_loopback: bool) -> str:
    """The address to listen on; a non-loopback one only if the vehicle file allows it."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError as exc:
        raise ValueError(f"live_view.host {host!r} is not an IP address") from exc
    if not address.is_loopback and not allow_non_loopback:
        raise ValueError(
            f"live_view.host {host} is not a loopback address: set "
            "live_view.allow_non_loopback = true to serve other machines"
        )
    return host


class RateGate:
    """At most one pass per ``1 / max_rate_hz`` per key (times from the caller)."""

    def __init__(self, max_rate_hz: float) -> None:
        self.min_interval_s = 1.0 / max_rate_hz
        self._last: dict[str, float] = {}

    def update(self, key: str, now_s: float) -> bool:
        last = self._last.get(key, -math.inf)
        if now_s - last < self.min_interval_s:
            return False
        self._last[key] = now_s
        return True


def _time(log_time_ns: int) -> Timestamp:
    return Timestamp(sec=log_time_ns // 1_000_000_000, nsec=log_time_ns % 1_000_000_000)


def _pose(x_m: float, y_m: float, yaw_rad: float) -> Pose:
    return Pose(
        position=Vector3(x=x_m, y=y_m, z=0.0),
        orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2)),
    )


class LiveView:
    """Publishes to Foxglove's channels; `run` is the service that owns the server."""

    def __init__(
        self,
        config: VehicleConfig,
        clock_offset_ns: int,
        context: Context | None = None,
    ) -> None:
        params = config.live_view
        self.host = check_host(params.host, params.allow_non_loopback)
        self.port = params.port
        self.context = context if context is not None else Context()
        self.gate = RateGate(params.max_rate_hz)
        self.clock_offset_ns = clock_offset_ns
        self.server: Any = None
        self.published = 0
        self.scans = {
            side: LaserScanChannel(f"/scan/{side}", context=self.context)
            for side in ("left", "right")
        }
        self.pose = PoseInFrameChannel("/dbw/pose", context=self.context)
        self.transform = FrameTransformChannel("/tf", context=self.context)
        self.log_channel = LogChannel("/log", context=self.context)
        self.status = Channel(
            "/dbw/status", schema=STATUS_SCHEMA, message_encoding="json", context=self.context
        )
        self.gnss_pose = PoseInFrameChannel("/dbw/gnss_pose", context=self.context)
        self.route = SceneUpdateChannel("/dbw/route", context=self.context)
        self.route_gate = RateGate(ROUTE_RATE_HZ)
        # The route source's points near the vehicle (``RouteAutopilot.route_window``);
        # None: the vehicle follows no routes.
        self.route_window: Callable[[], Mapping[str, Any]] | None = None

    # ---- taps (event loop; cheap when nobody watches) -----------------------------------
    def attach(self, topics: TopicRegistry) -> None:
        for side in ("left", "right"):
            name = f"scan.{side}"
            if name in dict(topics.items()):
                topics.get(name).subscribe(self._scan_listener(side))

    def _scan_listener(self, side: str) -> Callable[[Sample[Any]], None]:
        channel = self.scans[side]

        def listener(sample: Sample[Any]) -> None:
            if not channel.has_sinks() or not self.gate.update(channel.topic(), sample.stamp_s):
                return
            value = sample.value
            if isinstance(value, MountedScan):
                channel.log(self.laser_scan(value, self._ns(sample.stamp_s)))
                self.published += 1

        return listener

    def on_cycle(self, now_s: float, inputs: ControlInputs, output: CoreOutput) -> None:
        log_ns = self._ns(now_s)
        for note in output.notes:  # rare and wanted: never rate-limited
            if self.log_channel.has_sinks():
                fields = " ".join(f"{k}={v}" for k, v in note.fields.items())
                self.log_channel.log(
                    Log(
                        timestamp=_time(log_ns),
                        level=_LEVELS.get(note.event, LogLevel.Info),
                        message=f"{note.event} [{output.mode}] {fields}".rstrip(),
                        name="dbw.core",
                        file="",
                        line=0,
                    ),
                    log_time=log_ns,
                )
        pose = output.pc104_pose
        if pose is not None and self.transform.has_sinks() and self.gate.update("/tf", now_s):
            half_yaw = pose.yaw_rad / 2.0
            self.transform.log(
                FrameTransform(
                    timestamp=_time(log_ns),
                    parent_frame_id="launcher",
                    child_frame_id="vehicle",
                    translation=Vector3(x=pose.x_m, y=pose.y_m, z=0.0),
                    rotation=Quaternion(x=0.0, y=0.0, z=math.sin(half_yaw), w=math.cos(half_yaw)),
                ),
                log_time=log_ns,
            )
        if pose is not None and self.pose.has_sinks() and self.gate.update("/dbw/pose", now_s):
            self.pose.log(
                PoseInFrame(
                    timestamp=_time(log_ns),
                    frame_id="launcher",
                    pose=_pose(pose.x_m, pose.y_m, pose.yaw_rad),
                ),
                log_time=log_ns,
            )
        self._gnss_and_route(inputs, now_s, log_ns)
        if self.status.has_sinks() and self.gate.update("/dbw/status", now_s):
            self.status.log(json.dumps(self.status_message(output)), log_time=log_ns)
            self.published += 1

    def _gnss_and_route(self, inputs: ControlInputs, now_s: float, log_ns: int) -> None:
        gnss = inputs.gnss
        if (
            isinstance(gnss, GnssPose)
            and gnss.yaw_rad is not None
            and self.gnss_pose.has_sinks()
            and self.gate.update("/dbw/gnss_pose", now_s)
        ):
            self.gnss_pose.log(
                PoseInFrame(
                    timestamp=_time(log_ns),
                    frame_id="enu",
                    pose=_pose(gnss.east_m, gnss.north_m, gnss.yaw_rad),
                ),
                log_time=log_ns,
            )
            self.published += 1
        window = self.route_window
        if window is None or not self.route.has_sinks():
            return
        if not self.route_gate.update("/dbw/route", now_s):
            return
        self.route.log(self.route_scene(window(), log_ns), log_time=log_ns)
        self.published += 1

    @staticmethod
    def route_scene(window: Mapping[str, Any], log_ns: int) -> SceneUpdate:
        """The route near the vehicle as one line entity (replacing the last by its id)."""
        points = [Point3(x=float(e), y=float(n), z=0.0) for e, n in window.get("points_m", [])]
        line = LinePrimitive(
            type=LinePrimitiveLineType.LineStrip,
            thickness=3.0,
            scale_invariant=True,
            points=points,
            color=Color(r=0.43, g=0.30, b=0.25, a=1.0),
        )
        entity = SceneEntity(timestamp=_time(log_ns), frame_id="enu", id="route", lines=[line])
        return SceneUpdate(entities=[entity])

    def status_message(self, output: CoreOutput) -> dict[str, Any]:
        return {
            "now_s": output.now_s,
            "mode": str(output.mode),
            "engaged": output.engaged,
            "speed_setpoint_mps": output.speed_setpoint_mps,
            "steer_tyre_rad": output.steer_tyre_rad,
            "commands": describe_commands(output),
            "operator": {
                "steering_override": output.operator.steering_override,
                "brake_pedal": output.operator.brake_pedal,
                "throttle_pedal": output.operator.throttle_pedal,
            },
        }

    def laser_scan(self, scan: MountedScan, log_time_ns: int) -> LaserScan:
        angles = scan.angles_vehicle_rad
        rssi = scan.scan.channel("RSSI1")
        return LaserScan(
            timestamp=_time(log_time_ns),
            frame_id="vehicle",
            pose=_pose(scan.mount.x_m, scan.mount.y_m, 0.0),
            start_angle=float(angles[0]) if len(angles) else 0.0,
            end_angle=float(angles[-1]) if len(angles) else 0.0,
            ranges=scan.scan.ranges_m.tolist(),
            intensities=[] if rssi is None else rssi.data.astype(float).tolist(),
        )

    def _ns(self, monotonic_s: float) -> int:
        return int(monotonic_s * 1e9) + self.clock_offset_ns

    # ---- the service ----------------------------------------------------------------------
    async def run(self, ctx: ServiceContext) -> None:
        self.server = foxglove.start_server(
            name="dbw-applique", host=self.host, port=self.port, context=self.context
        )
        log.info("live_view_listening", host=self.host, port=self.server.port)
        try:
            while True:
                ctx.beat()
                await asyncio.sleep(BEAT_S)
        finally:
            server, self.server = self.server, None
            if server is not None:
                server.stop()
                log.info("live_view_stopped")

    @property
    def bound_port(self) -> int | None:
        return None if self.server is None else int(self.server.port)
