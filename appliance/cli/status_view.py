"""`dbw status` as text: the daemon's status document rendered for a person, pure.

The document comes over a socket from a daemon of maybe another version, so every field
is read defensively: a missing or odd value prints as "?" rather than a traceback, and
strings are cut and cleaned before they reach the terminal.
"""

from __future__ import annotations

import json
import math
from typing import Any


def render_status(doc: dict[str, Any]) -> str:
    """A compact human view of the daemon's status document.

    Every key is optional and may hold anything: what is there and makes sense is shown,
    nothing here raises.
    """
    if not isinstance(doc, dict):
        doc = {}
    lines = [_headline(doc)]
    speed = speed_line(doc)
    if speed:
        lines.append(speed)
    pedal = as_dict(doc.get("pedal_speed"))
    if pedal:  # the pedals speed path: what our throttle/brake controller is doing, and why
        state, reason = pedal.get("state"), pedal.get("reason")
        line = f"pedals: {clean_text(state) if isinstance(state, str) else '?'}"
        reference = _finite(pedal.get("reference_speed_mps"))
        if reference is not None:
            line += f", reference {reference:.2f} m/s"
        if isinstance(reason, str) and reason:
            line += f" ({clean_text(reason)})"
        lines.append(line)
    sweep = as_dict(doc.get("pedal_sweep"))
    if sweep:  # `dbw calibrate pedals` has armed the daemon's sweep
        phase = sweep.get("phase")
        run, runs = sweep.get("run"), sweep.get("runs")
        line = f"pedal sweep: {clean_text(phase) if isinstance(phase, str) else '?'}"
        if isinstance(run, int) and isinstance(runs, int):
            line += f", run {run}/{runs}"
        throttle, brake = _finite(sweep.get("throttle_pct")), _finite(sweep.get("brake_pct"))
        if throttle is not None and brake is not None:
            line += f", throttle {throttle:.0f} %, brake {brake:.0f} %"
        lines.append(line)
    palm = as_dict(doc.get("palm_tree"))
    if palm:  # `dbw calibrate palm-tree --auto` has armed the daemon's arcs
        lines.append(_palm_tree_line(palm))
    tuning = as_dict(as_dict(doc.get("autopilot")).get("tuning"))
    if tuning:  # `dbw calibrate lookahead` has armed the route source's runs
        lines.append(_tuning_line(tuning))
    torque = as_dict(doc.get("servo_torque"))
    if torque:  # the servo's load against the look-ahead tuning's
        retune, reason = torque.get("retune"), torque.get("reason")
        change = _finite(torque.get("change_pct"))
        if retune is True:
            text = "CHANGED since the look-ahead was tuned: re-tune it"
        elif retune is False:
            text = "as tuned" + (f" ({change:+.0f} %)" if change is not None else "")
        else:
            text = "not judged yet"
        if isinstance(reason, str) and reason and retune is not False:
            text += f" ({clean_text(reason)})"
        lines.append(f"servo torque: {text}")
    hold = as_dict(doc.get("hold_to_move"))
    if hold.get("required") is True:
        held = "held" if hold.get("held") is True else "not held"
        lines.append(f"hold-to-move: required, {held}")
    if doc.get("estop_latched") is True:
        lines.append("E-STOP LATCHED: `dbw estop-reset` once the vehicle is safe")
    blockers = as_strings(doc.get("engage_blockers"))
    if doc.get("mode") == "ready" and "engage_blockers" in doc:
        if blockers:
            lines.append("engage now: would be refused:")
            lines += [f"  - {reason}" for reason in blockers]
        else:
            lines.append("engage now: would be accepted")
    refusals = as_strings(doc.get("last_refusal"))
    if refusals:
        lines.append("last refusal:")
        lines += [f"  - {reason}" for reason in refusals]
    lines += _faults(doc)
    lines += _autopilot(doc)
    lines += _inputs(doc)
    lines += _name_table("commands", doc.get("commands"))
    overrides = as_dict(doc.get("overrides"))
    if overrides:
        active = [clean_text(name) for name, on in overrides.items() if on is True]
        lines.append("overrides: " + (", ".join(active) if active else "none"))
    loop = _loop_line(doc)
    if loop:
        lines.append(loop)
    event_loop = _event_loop_line(doc)
    if event_loop:
        lines.append(event_loop)
    lines += _name_table("links", doc.get("links"))
    system = _system_line(doc)
    if system:
        lines.append(system)
    recording = _recording_line(doc)
    if recording:
        lines.append(recording)
    tablet = as_dict(doc.get("tablet"))
    if tablet:
        paired = "paired" if tablet.get("paired") else "not paired"
        held = ", held" if tablet.get("held") else ""
        lines.append(
            f"tablet: {tablet.get('address')} {paired}{held}, pairing code "
            f"{tablet.get('pairing_code')} ({tablet.get('refused_requests', 0)} refused)"
        )
    lines += _name_table("services", doc.get("services"))
    return "\n".join(lines)


def _system_line(doc: dict[str, Any]) -> str:
    """One line: the PC's load, memory, disk and temperature, and any probe problem."""
    system = as_dict(doc.get("system"))
    if not system:
        return ""
    parts = []
    load, cpus = _finite(system.get("load_1m")), system.get("cpu_count")
    if load is not None:
        parts.append(f"load {load:.2f}" + (f"/{cpus} CPUs" if isinstance(cpus, int) else ""))
    memory = _finite(system.get("memory_available_mb"))
    if memory is not None:
        parts.append(f"{memory:.0f} MB memory free")
    disk = _finite(system.get("disk_free_mb"))
    if disk is not None:
        parts.append(f"{disk / 1e3:.1f} GB disk free")
    temperature = _finite(system.get("temperature_c"))
    parts.append(f"{temperature:.0f} degC" if temperature is not None else "no temperature sensor")
    jumps = system.get("clock_jumps")
    if isinstance(jumps, int) and jumps:
        parts.append(f"{jumps} wall-clock jumps")
    problem = system.get("problem")
    if isinstance(problem, str) and problem:
        parts.append(clean_text(problem))
    return "system: " + ", ".join(parts)


def _recording_line(doc: dict[str, Any]) -> str:
    """One line: where the recorder writes, how much, and anything it dropped."""
    rec = as_dict(doc.get("recording"))
    if not rec:
        return ""
    state = clean_text(rec.get("state")) if isinstance(rec.get("state"), str) else "starting"
    parts = [state]
    reason = rec.get("reason")
    if isinstance(reason, str) and reason:
        parts.append(clean_text(reason))
    if isinstance(rec.get("file"), str):
        parts.append(clean_text(rec.get("file")))
    written = _finite(rec.get("bytes"))
    if written is not None:
        parts.append(f"{written / 1e6:.1f} MB written")
    dropped: dict[str, Any] = {}
    for key in ("dropped_in_daemon", "dropped"):
        for name, count in as_dict(rec.get(key)).items():
            if isinstance(count, int) and count:
                dropped[clean_text(name)] = dropped.get(clean_text(name), 0) + count
    parts.append(
        "dropped " + ", ".join(f"{n} {k}" for k, n in sorted(dropped.items()))
        if dropped
        else "nothing dropped"
    )
    return "recording: " + "; ".join(parts)


def _headline(doc: dict[str, Any]) -> str:
    mode = clean_text(doc.get("mode")).upper() if doc.get("mode") is not None else ""
    head = mode or "UNKNOWN MODE"
    since_s = _finite(doc.get("mode_since_s"))
    if since_s is not None:
        head += f" for {format_duration(since_s)}"
    about = []
    if doc.get("vehicle") is not None:
        about.append(f"vehicle {clean_text(doc.get('vehicle'))}")
    uptime_s = _finite(doc.get("uptime_s"))
    if uptime_s is not None:
        about.append(f"up {format_duration(uptime_s)}")
    return head + (f"  ({', '.join(about)})" if about else "")


def speed_line(doc: dict[str, Any]) -> str:
    set_mps = _finite(doc.get("set_speed_mps"))
    measured_mps = _finite(doc.get("measured_speed_mps"))
    parts = []
    if "set_speed_mps" in doc:
        parts.append(f"set {set_mps:.2f} m/s" if set_mps is not None else "set -")
    if measured_mps is not None:
        parts.append(f"measured {measured_mps:.2f} m/s")
    return "speed: " + ", ".join(parts) if parts else ""


def _autopilot(doc: dict[str, Any]) -> list[str]:
    """The source's own view: for docking, the pose on the launcher and the plan."""
    pilot = as_dict(doc.get("autopilot"))
    lines = []
    localization = as_dict(pilot.get("localization"))
    if localization:
        status_value, reason_value = localization.get("status"), localization.get("reason")
        status = clean_text(status_value) if isinstance(status_value, str) else "?"
        quality = _finite(localization.get("quality"))
        reason = clean_text(reason_value) if isinstance(reason_value, str) else ""
        head = f"localization: {status}"
        if quality is not None:
            head += f", quality {quality:.0f}"
        lines.append(head + (f" ({reason})" if reason else ""))
        pose = as_dict(localization.get("pose"))
        x, y, h = (_finite(pose.get(k)) for k in ("x_m", "y_m", "heading_deg"))
        sx, sy, sh = (_finite(pose.get(k)) for k in ("sigma_x_m", "sigma_y_m", "sigma_heading_deg"))
        if None not in (x, y, h, sx, sy, sh):
            lines.append(
                f"  pose on the launcher: x {x:+.3f} m ±{sx:.3f}, y {y:+.3f} m ±{sy:.3f}, "
                f"heading {h:+.2f} deg ±{sh:.2f}"
            )
    docking = as_dict(pilot.get("docking"))
    gap, lateral = _finite(docking.get("gap_m")), _finite(docking.get("lateral_m"))
    if gap is not None and lateral is not None:
        phase_value, pattern_value = docking.get("phase"), docking.get("pattern")
        phase = clean_text(phase_value) if isinstance(phase_value, str) else "?"
        pattern = clean_text(pattern_value) if isinstance(pattern_value, str) else ""
        line = f"docking: {phase}, gap {gap * 1000:.0f} mm, lateral {lateral * 1000:+.1f} mm"
        if pattern:
            switches = _finite(docking.get("pattern_switches"))
            line += f", {pattern}" + (f" ({switches:.0f} switches)" if switches is not None else "")
        lines.append(line)
    lines += _route_lines(pilot, doc)
    lines += _pallet_lines(pilot)
    refused, source = pilot.get("refused"), pilot.get("source")
    if isinstance(refused, str) and refused:
        name = clean_text(source) if isinstance(source, str) else "?"
        lines.append(f"autopilot ({name}): refuses: {clean_text(refused)}")
    return lines


def _pallet_lines(pilot: dict[Any, Any]) -> list[str]:
    """The pallet source: the pose on the posts, the merge, the target and the approach."""
    if "merged" not in pilot:
        return []
    lines = []
    localization = as_dict(pilot.get("localization"))
    pose = as_dict(localization.get("pose"))
    x, y, h = (_finite(pose.get(k)) for k in ("x_m", "y_m", "yaw_deg"))
    if x is not None and y is not None and h is not None:
        posts = [clean_text(p, 24) for p in _list(localization.get("landmarks"))]
        lines.append(
            f"  pose on the posts: x {x:+.3f} m, y {y:+.3f} m, heading {h:+.2f} deg "
            f"({', '.join(posts) or 'no post in view'})"
        )
    target, phase = pilot.get("target"), pilot.get("phase")
    head = "pallet: " + (clean_text(target) if isinstance(target, str) else "none selected")
    head += f", {clean_text(phase)}" if isinstance(phase, str) else ""
    head += "" if pilot.get("merged") else " (maps not merged)"
    approach = as_dict(pilot.get("approach"))
    lateral, heading = _finite(approach.get("lateral_mm")), _finite(approach.get("heading_deg"))
    distance = _finite(approach.get("distance_m"))
    if lateral is not None and heading is not None and distance is not None:
        head += f", {distance:.2f} m to go, lateral {lateral:+.1f} mm, heading {heading:+.2f} deg"
    lines.append(head)
    return lines


def _route_lines(pilot: dict[Any, Any], doc: dict[str, Any]) -> list[str]:
    """The route source: the route, progress, cross-track and look-ahead (Stanley's GUI),
    and the routes near the vehicle with whether engagement would be allowed."""
    lines = []
    name = pilot.get("route")
    if "route" in pilot:
        selection = pilot.get("selection")
        head = f"route: {clean_text(name)}" if isinstance(name, str) else "route: none selected"
        if isinstance(selection, str) and selection != "ok":
            head += f" ({clean_text(selection)})"
        follow = as_dict(pilot.get("follow"))
        progress, remaining = _finite(follow.get("progress_m")), _finite(follow.get("remaining_m"))
        if progress is not None and remaining is not None:
            head += f", {progress:.0f} m driven, {remaining:.0f} m to go"
        cross, lookahead = _finite(follow.get("cross_track_m")), _finite(follow.get("lookahead_m"))
        if cross is not None:
            head += f", cross-track {cross * 100:+.1f} cm"
        if lookahead is not None:
            head += f", look-ahead {lookahead:.1f} m"
        fix = follow.get("fix")
        if isinstance(fix, str) and fix != "ok":
            head += f"; fix: {clean_text(fix)}"
        lines.append(head)
    for nearby in _list(doc.get("routes_nearby")):
        entry = as_dict(nearby)
        distance, heading = (
            _finite(entry.get("distance_m")),
            _finite(entry.get("heading_error_deg")),
        )
        if distance is None or heading is None:
            continue
        verdict = "engage allowed" if entry.get("engage_allowed") is True else "too far or turned"
        lines.append(
            f"  nearby: {clean_text(entry.get('name'))} {distance:.1f} m, "
            f"heading {heading:.0f} deg off: {verdict}"
        )
    return lines


def _faults(doc: dict[str, Any]) -> list[str]:
    lines = []
    if "faults" in doc:
        faults = [as_dict(fault) for fault in _list(doc.get("faults"))]
        if not isinstance(doc.get("faults"), list):
            lines.append(f"faults: unreadable ({clean_text(doc.get('faults'), 40)})")
        elif not faults:
            lines.append("faults: none")
        else:
            lines.append(f"faults ({len(faults)}):")
            for fault in faults:
                line = f"  {clean_text(fault.get('key', '?'))}"
                if fault.get("detail"):
                    line += f": {clean_text(fault.get('detail'))}"
                age_s = _finite(fault.get("since_s"))
                if age_s is not None:
                    line += f" (for {format_duration(age_s)})"
                lines.append(line)
    history = [as_dict(entry) for entry in _list(doc.get("fault_history"))]
    if history:
        latest = history[-1]
        lines.append(
            f"fault history: {len(history)} cleared, latest {clean_text(latest.get('key', '?'))}"
        )
    return lines


def _inputs(doc: dict[str, Any]) -> list[str]:
    inputs = as_dict(doc.get("inputs"))
    if not inputs:
        return []
    rows = []
    for name, raw in inputs.items():
        entry = as_dict(raw)
        age = entry.get("age_s", "?")
        age_s = _finite(age)
        if age is None or (_number(age) is not None and age_s is None):
            age_text = "never"  # null or infinite: nothing has arrived yet
        else:
            age_text = format_duration(age_s) if age_s is not None else "?"
        limit_s = _finite(entry.get("limit_s"))
        flags = []
        if entry.get("stale") is True:
            flags.append("STALE")
        if entry.get("critical") is True:
            flags.append("critical")
        rows.append(
            (
                clean_text(name),
                age_text,
                format_duration(limit_s) if limit_s is not None else "-",
                " ".join(flags),
            )
        )
    width = min(max(5, *(len(row[0]) for row in rows)), 32)
    lines = [f"inputs:{'':{width - 5}} {'age':>8} {'limit':>8}"]
    for name, age_text, limit_text, flags_text in rows:
        lines.append(f"  {name:<{width}} {age_text:>8} {limit_text:>8}  {flags_text}".rstrip())
    return lines


def _name_table(title: str, value: object) -> list[str]:
    table = as_dict(value)
    if not table:
        return []
    width = min(max(len(clean_text(name)) for name in table), 24)
    return [f"{title}:"] + [
        f"  {clean_text(name):<{width}}  {clean_text(item)}" for name, item in table.items()
    ]


def _loop_line(doc: dict[str, Any]) -> str:
    loop = as_dict(doc.get("loop"))
    parts = []
    for key, template in (
        ("rate_hz", "{:.1f} Hz"),
        ("cycles", "{:.0f} cycles"),
        ("overruns", "{:.0f} overruns"),
        ("jitter_p99_ms", "jitter p99 {:.2f} ms"),
        ("step_p99_ms", "step p99 {:.2f} ms"),
    ):
        value = _finite(loop.get(key))
        if value is not None:
            parts.append(template.format(value))
    wakes_by = loop.get("wakes_by")
    if isinstance(wakes_by, str) and parts:
        parts.append(f"wakes by {clean_text(wakes_by)}")
    deferred = _finite(loop.get("work_deferred"))
    if deferred is not None and parts:
        parts.append(f"{deferred:.0f} deferred for a cycle")
    return "loop: " + ", ".join(parts) if parts else ""


def _event_loop_line(doc: dict[str, Any]) -> str:
    """Who held the event loop longest, in the last window and since start."""
    lag = as_dict(doc.get("event_loop"))
    disabled = as_dict(lag.get("since_start")).get("disabled")
    if disabled:
        return f"event loop: not monitored: {clean_text(disabled)}"
    longest = _finite(lag.get("longest_callback_ms"))
    if longest is None:
        return ""
    by = clean_text(lag.get("longest_callback_by"))
    line = f"event loop: longest callback {longest:.1f} ms ({by})"
    window = _finite(lag.get("window_s"))
    slow = _finite(lag.get("slow_callbacks"))
    busy = _finite(lag.get("busy_pct"))
    if window is not None and slow is not None:
        line += f", {slow:.0f} slow in the last {window:.1f} s"
    cpu = _finite(lag.get("cpu_pct"))
    if busy is not None:
        line += f", {busy:.0f} % busy"
        if cpu is not None:
            line += f" ({cpu:.0f} % CPU)"
    worst = as_dict(lag.get("since_start"))
    worst_ms = _finite(worst.get("longest_callback_ms"))
    if worst_ms is not None:
        by = clean_text(worst.get("longest_callback_by"))
        line += f"; worst since start {worst_ms:.1f} ms ({by})"
    return line


def format_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "never"
    if abs(seconds) < 1.0:
        return f"{seconds * 1e3:.0f} ms"
    if abs(seconds) < 120.0:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(int(seconds), 60)
    if minutes < 120:
        return f"{minutes} min {secs} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes} min"


def _number(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        return float(value)
    except OverflowError:  # an integer too large for a float
        return math.inf if value > 0 else -math.inf


def _finite(value: object) -> float | None:
    number = _number(value)
    return number if number is not None and math.isfinite(number) else None


def as_dict(value: object) -> dict[Any, Any]:
    return value if isinstance(value, dict) else {}


def _list(value: object) -> list[Any]:
    return value if isinstance(value, list) else []


def as_strings(value: object) -> list[str]:
    if value is None or value == "" or value == []:
        return []
    items = value if isinstance(value, list) else [value]
    return [clean_text(item) for item in items]


def clean_text(value: object, limit: int = 160) -> str:
    """One printable line (the daemon's strings may hold anything, even escape codes)."""
    if not isinstance(value, str):
        try:
            value = json.dumps(value, default=str)
        except (TypeError, ValueError, RecursionError):
            value = "?"
    text = "".join(ch if ch.isprintable() else "?" for ch in value[: limit + 1])
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _palm_tree_line(palm: dict[str, Any]) -> str:
    phase, arc, arcs = palm.get("phase"), palm.get("arc"), palm.get("arcs")
    line = f"palm tree: {clean_text(phase) if isinstance(phase, str) else '?'}"
    if isinstance(arc, int) and isinstance(arcs, int):
        line += f", arc {arc}/{arcs}"
    wheel, driven = _finite(palm.get("wheel_target_rad")), _finite(palm.get("driven_m"))
    if wheel is not None:
        line += f", wheel {wheel:+.2f} rad"
    if driven is not None:
        line += f", {driven:.1f} m driven"
    stuck = palm.get("stuck")
    if isinstance(stuck, str) and stuck:
        line += f" (STUCK: {clean_text(stuck)})"
    return line


def _tuning_line(tuning: dict[str, Any]) -> str:
    phase, run, runs = tuning.get("phase"), tuning.get("run"), tuning.get("runs")
    line = f"look-ahead runs: {clean_text(phase) if isinstance(phase, str) else '?'}"
    if isinstance(run, int) and isinstance(runs, int):
        line += f", run {run + 1}/{runs}"
    described = tuning.get("describe")
    if isinstance(described, str):
        line += f" ({clean_text(described)})"
    left = _finite(tuning.get("test_left_s"))
    if left is not None and phase == "test":
        line += f", {left:.0f} s of test left"
    if tuning.get("stopping") is True:
        line += ", stopping on its course: disengage to take over"
    return line
