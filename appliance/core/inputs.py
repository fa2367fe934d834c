"""What the control core sees each cycle: the latest value of every input and its age.

The control loop builds one :class:`ControlInputs` per cycle from the topics; tests build
them by hand. Values are the latest ones whatever their age; freshness is judged in the
core against the config's age limits (``ages_s``), so a stale value is never used as if
it were fresh, and a missing one is stale (deny by default).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from appliance.localization.gnss_pose import GnssNoFix, GnssPose
from drivers.actuators.messages import (
    BrakeTelemetry,
    PanelTelemetry,
    SteeringTelemetry,
    ThrottleTelemetry,
)
from drivers.lms111.mounted import MountedScan
from drivers.pc104.messages import Pc104Status
from drivers.system.probes import SystemHealth


@dataclass(frozen=True)
class LinkCounts:
    """Monotonic totals of a link, for the error-budget rule (they may reset on restart)."""

    errors: int = 0  # CRC + counter + length/range failures
    good: int = 0  # frames accepted


TABLET_HOLD_TOPIC = "tablet.hold"  # where the tablet page publishes its hold


@dataclass(frozen=True)
class TabletHold:
    """The tablet's hold-to-move button as its gate last saw it (`appliance.tablet_page`):
    held until ``until_s`` (the control loop's clock) unless a later word says otherwise.
    The core lets it lapse at ``until_s`` itself: a frozen page says nothing more."""

    held: bool
    until_s: float


@dataclass(frozen=True)
class ControlInputs:
    ages_s: Mapping[str, float]
    steering: SteeringTelemetry | None = None
    throttle: ThrottleTelemetry | None = None
    brake: BrakeTelemetry | None = None
    panel: PanelTelemetry | None = None
    panel_seq: int | None = None
    pc104_status: Pc104Status | None = None
    pc104_link: LinkCounts = LinkCounts()
    scans: Mapping[str, MountedScan | None] = field(default_factory=dict)
    # Critical services the supervisor reports as not running (name -> state and reason).
    service_faults: Mapping[str, str] = field(default_factory=dict)
    # The GNSS/INS receiver's latest epoch and its sequence number: a source that needs
    # every epoch (the route's transform) takes each new one once.
    gnss: GnssPose | GnssNoFix | None = None
    gnss_seq: int | None = None
    # The PC's own health (appliance/system_monitor.py), where the daemon monitors it.
    system: SystemHealth | None = None
    # The tablet page's hold (a forklift guided from a tablet), where the daemon serves it.
    tablet: TabletHold | None = None
    # The keys of the source's background jobs that have finished (`appliance.core.jobs`):
    # when a plan became available is an input, so replay takes it at the same cycle.
    jobs_done: tuple[float, ...] = ()
