"""What a recording holds: its channels, their schemas, and how each message is encoded.

Two kinds of channel, for two readers:

- ``/dbw/...`` channels are for replay: every topic sample, every control cycle (the
  inputs the core saw and the output it made), every request the control socket passed
  to the core, every restart of the core, in the exact typed JSON of `codec`. Their
  schema names say the Python type, so a reader rebuilds the objects from an allow-list
  (`SAMPLE_TYPES`), never by importing a name a file gives it.
- Foxglove's well-known schemas (``foxglove.LaserScan``, ``foxglove.Log``,
  ``foxglove.PoseInFrame``) for looking: a recording opens in Foxglove with no plug-in.

Everything here is pure: messages in, ``(ChannelSpec, bytes)`` out.
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from appliance.core.inputs import ControlInputs
from appliance.core.output import CoreOutput, Note
from appliance.localization.gnss_pose import GnssNoFix, GnssPose
from appliance.recording.codec import encode
from appliance.recording.fastcodec import encode_fast
from appliance.recording.files import ChannelSpec
from drivers.actuators.messages import (
    BrakeTelemetry,
    PanelTelemetry,
    SteeringTelemetry,
    ThrottleTelemetry,
)
from drivers.lms111.mounted import MountedScan
from drivers.pc104.messages import (
    Inclinometer,
    MotorPulses,
    Pc104Heartbeat,
    Pc104Status,
    WheelAngles,
)
from drivers.system.probes import SystemHealth

CYCLE_TOPIC = "/dbw/cycle"
REQUEST_TOPIC = "/dbw/request"
RESET_TOPIC = "/dbw/reset"
RECORDER_TOPIC = "/dbw/recorder"
SAMPLE_TOPIC_PREFIX = "/dbw/topic/"
LOG_TOPIC = "/log"
SAMPLE_SCHEMA_PREFIX = "dbw.sample:"
VEHICLE_FRAME = "vehicle"

# Every type a topic publishes, by the name its channel's schema carries.
SAMPLE_TYPES: dict[str, type] = {
    cls.__name__: cls
    for cls in (
        SteeringTelemetry,
        ThrottleTelemetry,
        BrakeTelemetry,
        PanelTelemetry,
        Pc104Status,
        WheelAngles,
        MotorPulses,
        Inclinometer,
        Pc104Heartbeat,
        MountedScan,
        GnssPose,
        GnssNoFix,
        SystemHealth,
    )
}
# A topic whose values are of no known type is still recorded, as free JSON.
FREE_SAMPLE = "any"


def _schema(title: str, description: str, properties: Mapping[str, Any] | None = None) -> bytes:
    schema: dict[str, Any] = {"title": title, "description": description, "type": "object"}
    if properties:
        schema["properties"] = properties
    return json.dumps(schema).encode()


_TIME = {
    "type": "object",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
}
_VECTOR3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUATERNION = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_POSE = {"type": "object", "properties": {"position": _VECTOR3, "orientation": _QUATERNION}}

LASER_SCAN_SCHEMA = _schema(
    "foxglove.LaserScan",
    "A single scan from a planar laser range-finder",
    {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": _POSE,
        "start_angle": {"type": "number"},
        "end_angle": {"type": "number"},
        "ranges": {"type": "array", "items": {"type": "number"}},
        "intensities": {"type": "array", "items": {"type": "number"}},
    },
)
LOG_SCHEMA = _schema(
    "foxglove.Log",
    "A log message",
    {
        "timestamp": _TIME,
        "level": {"type": "integer", "enum": [0, 1, 2, 3, 4, 5]},
        "message": {"type": "string"},
        "name": {"type": "string"},
        "file": {"type": "string"},
        "line": {"type": "integer"},
    },
)
FRAME_TRANSFORM_SCHEMA = _schema(
    "foxglove.FrameTransform",
    "A transform between two reference frames in 3D space",
    {
        "timestamp": _TIME,
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _VECTOR3,
        "rotation": _QUATERNION,
    },
)
POSE_IN_FRAME_SCHEMA = _schema(
    "foxglove.PoseInFrame",
    "A timestamped pose for an object or reference frame in 3D space",
    {"timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE},
)

CYCLE_CHANNEL = ChannelSpec(
    CYCLE_TOPIC,
    "dbw.cycle",
    _schema(
        "dbw.cycle",
        "One control cycle: the time, the inputs the core saw (scans by their sample's "
        "seq), the output it made. Exact typed JSON (appliance/recording/codec.py).",
    ),
)
REQUEST_CHANNEL = ChannelSpec(
    REQUEST_TOPIC,
    "dbw.request",
    _schema("dbw.request", "A control-socket request handed to the core, and its answer"),
)
RESET_CHANNEL = ChannelSpec(
    RESET_TOPIC, "dbw.reset", _schema("dbw.reset", "The control loop (re)started its core")
)
RECORDER_CHANNEL = ChannelSpec(
    RECORDER_TOPIC,
    "dbw.recorder",
    _schema("dbw.recorder", "The recorder's own counts: what it dropped and why"),
)
LOG_CHANNEL = ChannelSpec(LOG_TOPIC, "foxglove.Log", LOG_SCHEMA)


def sample_channel(topic: str, type_name: str) -> ChannelSpec:
    name = SAMPLE_SCHEMA_PREFIX + type_name
    return ChannelSpec(
        SAMPLE_TOPIC_PREFIX + topic,
        name,
        _schema(name, "Every sample of a daemon topic: seq, stamp_s (monotonic), value"),
    )


def sample_type_name(value: Any) -> str:
    name = type(value).__name__
    return name if SAMPLE_TYPES.get(name) is type(value) else FREE_SAMPLE


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _time(log_time_ns: int) -> dict[str, int]:
    return {"sec": log_time_ns // 1_000_000_000, "nsec": log_time_ns % 1_000_000_000}


def _yaw_quaternion(yaw_rad: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw_rad / 2.0), "w": math.cos(yaw_rad / 2.0)}


@dataclass(frozen=True)
class Encoded:
    spec: ChannelSpec
    data: bytes


def encode_sample(
    topic: str, log_time_ns: int, seq: int, stamp_s: float, value: Any
) -> Iterator[Encoded]:
    """A topic sample for replay, and a scan also as a foxglove.LaserScan to look at."""
    type_name = sample_type_name(value)
    declared = SAMPLE_TYPES.get(type_name, Any)
    payload = {"seq": seq, "stamp_s": encode(stamp_s, float), "value": encode_fast(value, declared)}
    yield Encoded(sample_channel(topic, type_name), _dumps(payload))
    if isinstance(value, MountedScan):
        yield Encoded(
            ChannelSpec(f"/{topic.replace('.', '/')}", "foxglove.LaserScan", LASER_SCAN_SCHEMA),
            _dumps(laser_scan(value, log_time_ns)),
        )


def laser_scan(scan: MountedScan, log_time_ns: int) -> dict[str, Any]:
    """A MountedScan as foxglove.LaserScan in the vehicle frame (0: no echo)."""
    angles = scan.angles_vehicle_rad
    ranges = scan.scan.ranges_m
    rssi = scan.scan.channel("RSSI1")
    return {
        "timestamp": _time(log_time_ns),
        "frame_id": VEHICLE_FRAME,
        "pose": {
            "position": {"x": scan.mount.x_m, "y": scan.mount.y_m, "z": 0.0},
            "orientation": _yaw_quaternion(0.0),
        },
        "start_angle": float(angles[0]) if len(angles) else 0.0,
        "end_angle": float(angles[-1]) if len(angles) else 0.0,
        # To 0.1 mm (the device resolves 1 mm): the shortest decimal text JSON can carry.
        "ranges": np.round(ranges, 4).tolist(),
        "intensities": [] if rssi is None else rssi.data.astype(float).tolist(),
    }


def encode_cycle(
    log_time_ns: int,
    now_s: float,
    inputs: ControlInputs,
    scan_seqs: Mapping[str, int | None],
    output: CoreOutput,
) -> Iterator[Encoded]:
    """A control cycle for replay; its notes also as foxglove.Log lines, and the pose the
    PC104 is given as a foxglove.PoseInFrame."""
    payload = {
        "now_s": encode(now_s, float),
        "inputs": encode_fast(inputs, ControlInputs),
        "scan_seqs": dict(scan_seqs),
        "output": encode_fast(output, CoreOutput),
    }
    yield Encoded(CYCLE_CHANNEL, _dumps(payload))
    for note in output.notes:
        yield Encoded(LOG_CHANNEL, _dumps(log_line(note, str(output.mode), log_time_ns)))
    pose = output.pc104_pose
    if pose is not None:
        # The vehicle frame in the launcher's: Foxglove's 3D panel then draws the scans
        # (frame "vehicle") where they are on the launcher.
        yield Encoded(
            ChannelSpec("/tf", "foxglove.FrameTransform", FRAME_TRANSFORM_SCHEMA),
            _dumps(
                {
                    "timestamp": _time(log_time_ns),
                    "parent_frame_id": "launcher",
                    "child_frame_id": VEHICLE_FRAME,
                    "translation": {"x": pose.x_m, "y": pose.y_m, "z": 0.0},
                    "rotation": _yaw_quaternion(pose.yaw_rad),
                }
            ),
        )
        yield Encoded(
            ChannelSpec("/dbw/pose", "foxglove.PoseInFrame", POSE_IN_FRAME_SCHEMA),
            _dumps(
                {
                    "timestamp": _time(log_time_ns),
                    "frame_id": "launcher",
                    "pose": {
                        "position": {"x": pose.x_m, "y": pose.y_m, "z": 0.0},
                        "orientation": _yaw_quaternion(pose.yaw_rad),
                    },
                }
            ),
        )


def cycle_ending(output: Any) -> bytes:
    """The last bytes of a cycle's message whose encoded output is ``output``
    (`encode_cycle` writes the output last): replay compares its own output's bytes with
    these before it decodes anything of the recorded one."""
    return b',"output":' + _dumps(output) + b"}"


_LEVELS = {"fault_raised": 4, "safe_stop": 4, "fault_cleared": 2}


def log_line(note: Note, mode: str, log_time_ns: int) -> dict[str, Any]:
    fields = encode(dict(note.fields))
    text = " ".join(f"{k}={v}" for k, v in fields.items())
    return {
        "timestamp": _time(log_time_ns),
        "level": _LEVELS.get(note.event, 2),
        "message": f"{note.event} [{mode}] {text}".rstrip(),
        "name": "dbw.core",
        "file": "",
        "line": 0,
    }


def encode_request(
    now_s: float | None, kind: str, name: str, accepted: bool, message: str
) -> Iterator[Encoded]:
    payload = {
        "now_s": encode(now_s, float | None),
        "kind": kind,
        "name": name,
        "accepted": accepted,
        "message": message,
    }
    yield Encoded(REQUEST_CHANNEL, _dumps(payload))


RAW_TOPIC_PREFIX = "/raw/"
RAW_BYTES_CHANNEL_SCHEMA = _schema(
    "dbw.raw.bytes",
    "Bytes as read from a link (an LMS111 socket, a board's or the GNSS receiver's serial "
    "port), with the monotonic time they were read: t_s, b64",
)
RAW_CAN_CHANNEL_SCHEMA = _schema(
    "dbw.raw.can",
    "A CAN frame as received: t_s (monotonic), id, ext, err, rtr, dlc, data (hex)",
)
# (arbitration id, extended, error frame, remote frame, dlc, data)
CanFrame = tuple[int, bool, bool, bool, int, bytes]


def encode_raw(source: str, kind: str, payload: Any, t_s: float) -> Iterator[Encoded]:
    """A link's raw input for the forensic record (replay works on samples)."""
    if kind == "can":
        can_id, ext, err, rtr, dlc, data = payload
        spec = ChannelSpec(RAW_TOPIC_PREFIX + source, "dbw.raw.can", RAW_CAN_CHANNEL_SCHEMA)
        body: dict[str, Any] = {
            "t_s": encode(t_s, float),
            "id": can_id,
            "ext": ext,
            "err": err,
            "rtr": rtr,
            "dlc": dlc,
            "data": bytes(data).hex(),
        }
    else:
        spec = ChannelSpec(RAW_TOPIC_PREFIX + source, "dbw.raw.bytes", RAW_BYTES_CHANNEL_SCHEMA)
        body = {"t_s": encode(t_s, float), "b64": base64.b64encode(payload).decode("ascii")}
    yield Encoded(spec, _dumps(body))


def encode_reset(now_s: float) -> Iterator[Encoded]:
    yield Encoded(RESET_CHANNEL, _dumps({"now_s": encode(now_s, float)}))


def encode_recorder_counts(counts: Mapping[str, Any]) -> Iterator[Encoded]:
    yield Encoded(RECORDER_CHANNEL, _dumps(encode(dict(counts))))
