"""What the daemon says about itself: the `systemctl status` line and the `dbw status` document.

Plain functions of what the daemon holds (the supervisor's snapshot, the core, the topics,
the loop's figures), so the words a person reads are built in one place, apart from the
lifecycle that owns those parts.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from appliance.core.core import ControlCore
from appliance.loop_monitor import LoopLag
from appliance.modes import Mode
from appliance.supervisor import LatchedError, ServiceState, ServiceStatus
from appliance.topics import TopicRegistry


def service_summary(snapshot: Iterable[ServiceStatus]) -> dict[str, str]:
    summary = {}
    for status in snapshot:
        age = status.heartbeat_age_s
        text = str(status.state)
        if math.isfinite(age):
            text += f" beat {age * 1e3:.0f} ms ago"
        if status.restarts:
            text += f", {status.restarts} restart(s)"
        summary[status.name] = text
    return summary


def status_line(
    latched: LatchedError | None, states: list[ServiceStatus], core: ControlCore
) -> str:
    """One line for `systemctl status`: what the daemon is doing, in words."""
    if latched is not None:
        return (
            f"ERROR (latched): critical service '{latched.service}' failed: {latched.reason}; "
            "vehicle held safe, restart the service to recover"
        )
    unhealthy = [s.name for s in states if s.critical and s.state is not ServiceState.RUNNING]
    restarts = sum(s.restarts for s in states)
    state = core.state
    head = str(state.mode).upper()
    if state.mode is Mode.SPEED_HOLD and state.set_speed_mps is not None:
        head += f" {state.set_speed_mps:.2f} m/s"
    if state.faults:
        head += ": " + "; ".join(f.reason for f in state.faults[:3])
    elif state.mode is Mode.READY and core.last_refusal:
        head += " (last refusal: " + "; ".join(core.last_refusal[:2]) + ")"
    if unhealthy:
        head = "DEGRADED: restarting " + ", ".join(unhealthy) + "; " + head
    return f"{head}; {len(states)} services, {restarts} restart(s)"


def status_document(
    *,
    vehicle: str,
    uptime_s: float,
    core: ControlCore,
    topics: TopicRegistry,
    loop: Mapping[str, Any],
    work_deferred: int,
    event_loop: LoopLag,
    event_loop_worst: Mapping[str, Any],
    services: dict[str, str],
    now_s: float,
    links: Mapping[str, str] | None = None,
    gnss: Mapping[str, Any] | None = None,
    recording: Mapping[str, Any] | None = None,
    system: Mapping[str, Any] | None = None,
    tablet: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """What `dbw status` shows: the core's view plus inputs, loop figures, services, and
    (given ``links``, `vehicle_io.link_summary`) one line per device link, and (given
    ``gnss``, `GnssInput.status`) the receiver's latest epoch."""
    doc: dict[str, Any] = {"vehicle": vehicle, "uptime_s": round(uptime_s, 3)}
    doc.update(core.status(now_s))
    ages = topics.ages_s(now_s)
    ages["steering.pot"] = ages.get("board.steering", math.inf)
    limits = core.staleness.age_limits_s
    critical = set(core.staleness.critical)
    if core.pedals:  # no PC104 on this vehicle: its status is no input, stale or not
        ages = {name: age for name, age in ages.items() if not name.startswith("pc104.")}
    doc["inputs"] = {
        name: {
            "age_s": round(age, 4) if math.isfinite(age) else None,
            "limit_s": limits.get(name),
            "stale": name in limits and not (math.isfinite(age) and age <= limits[name]),
            "critical": name in critical,
        }
        for name, age in sorted(ages.items())
    }
    # Scan decodes and heartbeats that waited for a cycle due (ControlSlot).
    doc["loop"] = {**loop, "work_deferred": work_deferred}
    doc["event_loop"] = {**event_loop.as_dict(), "since_start": event_loop_worst}
    doc["services"] = services
    if tablet is not None:
        doc["tablet"] = dict(tablet)
    if links is not None:
        doc["links"] = dict(links)
    if gnss is not None:  # the latest epoch, where the vehicle has a receiver
        doc["gnss"] = dict(gnss)
    if system is not None:  # the PC: load, memory, disk, temperature, clock jumps
        doc["system"] = dict(system)
    if recording is not None:  # the recorder's state, file, counts and drops
        doc["recording"] = dict(recording)
    if core.calibration_problem:
        doc["calibration"] = core.calibration_problem
    return doc
