"""What passes the autopilot seam: the cycle's observation in, a source's wish out.

Kept apart from the sources (``appliance.core.autopilot``) so a source in its own module
can use these types without importing the registry that imports it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

from appliance.localization.gnss_pose import GnssNoFix, GnssPose
from drivers.geometry import Pose2D
from drivers.lms111.mounted import MountedScan
from drivers.pc104.messages import MotionPattern, PoseState


@dataclass(frozen=True)
class Observation:
    """What a source may look at this cycle (all optional: inputs can be missing)."""

    now_s: float
    speed_mps: float | None
    steer_tyre_rad: float | None
    scans: Mapping[str, MountedScan | None] = field(default_factory=dict)
    # Whether the operator has engaged (a source that plans, like docking, starts its plan
    # afresh at each engagement and does not advance it while the operator drives).
    engaged: bool = False
    # The GNSS/INS receiver's latest epoch and its sequence number (a route source takes
    # each new epoch once).
    gnss: GnssPose | GnssNoFix | None = None
    gnss_seq: int | None = None
    # The source's background jobs that have finished (`appliance.core.jobs`).
    jobs_done: tuple[float, ...] = ()


@dataclass(frozen=True)
class AutopilotWish:
    """A source's wish for this cycle.

    ``ready=False`` refuses engagement with ``reason`` (and disengages if it happens while
    engaged: a source that lost its route cannot steer). ``max_speed_mps`` caps the
    operator's set speed (a route's speed limit); None leaves it alone. ``reverse`` asks
    for the set speed backwards, ``rear_steer_rad`` is the rear row's angle in the
    REAR_STEER pattern (physical, left positive); the limits apply to both. ``status`` is
    what the source has to say in `dbw status` (plain data: a pose, a phase, a gap).
    ``pose`` (with ``pose_state``) and ``expected_pose`` are the source's estimate of the
    geometric centre and where its plan takes it, in the site frame; the PC104 link
    carries them for a PC104 that closes the steering loop itself. ``speed_mps`` is a
    source that sets the speed itself (the palm tree's walking pace and its stops): in
    SPEED_HOLD it takes the place of the operator's set speed, under the same caps and
    ramp (0 stops and holds). ``pedals_pct``
    (throttle, brake) is a source that drives the pedals itself (the pedal sweep,
    ``appliance.core.pedal_sweep``): honoured only in SPEED_HOLD on the pedals path, in
    place of the speed controller, through the same arbitration and pedal limits.
    """

    ready: bool
    reason: str = ""
    steer_tyre_rad: float = 0.0
    max_speed_mps: float | None = None
    pattern: MotionPattern | None = None  # None: the vehicle's default pattern
    rear_steer_rad: float = 0.0
    reverse: bool = False
    status: Mapping[str, object] = field(default_factory=dict)
    pose: Pose2D | None = None
    pose_state: PoseState = PoseState.LOST
    expected_pose: Pose2D | None = None
    speed_mps: float | None = None
    pedals_pct: tuple[float, float] | None = None


class AutopilotSource(Protocol):
    name: str

    def reset(self) -> None: ...

    def update(self, observation: Observation) -> AutopilotWish: ...
