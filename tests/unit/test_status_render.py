"""`dbw status`'s human view: everything the daemon reports, and nothing that can crash it."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.cli.status_view import format_duration, render_status

FULL: dict[str, Any] = {
    "vehicle": "sim",
    "mode": "speed_hold",
    "mode_since_s": 12.3,
    "uptime_s": 40.1,
    "set_speed_mps": 1.5,
    "measured_speed_mps": 1.48,
    "hold_to_move": {"required": True, "held": False},
    "estop_latched": True,
    "last_refusal": ["critical input stale: scan.left", "brake pedal pressed"],
    "faults": [{"key": "stale:board.steering", "detail": "no frame for 0.3 s", "since_s": 3.2}],
    "fault_history": [
        {"key": "stale:scan.right", "detail": "...", "raised_s": 1.0, "cleared_s": 2.0}
    ],
    "inputs": {
        "board.steering": {"age_s": 0.012, "limit_s": 0.05, "stale": False, "critical": True},
        "scan.left": {"age_s": None, "limit_s": 0.1, "stale": True, "critical": True},
        "scan.right": {"age_s": math.inf, "limit_s": 0.1, "stale": True, "critical": True},
        "panel": {"age_s": 0.05, "limit_s": 0.2, "stale": False, "critical": False},
    },
    "commands": {
        "steering": "position 0.031 rad",
        "throttle": "released",
        "brake": "released 0 %",
        "pc104": "counter_steer 1.50 m/s front 0.031 rad",
        "lamps": "engaged",
    },
    "overrides": {"steering": False, "brake_pedal": True, "throttle_pedal": False},
    "loop": {
        "rate_hz": 50.0,
        "cycles": 2000,
        "overruns": 1,
        "jitter_p99_ms": 0.8,
        "step_p99_ms": 0.3,
        "wakes_by": "timerfd",
        "work_deferred": 12,
    },
    "services": {"control": "running beat 3 ms ago", "lms111_left": "backoff, 2 restart(s)"},
}


def line_with(text: str, needle: str) -> str:
    matches = [line for line in text.splitlines() if needle in line]
    assert matches, f"no line with {needle!r} in:\n{text}"
    return matches[0]


def row(text: str, name: str) -> list[str]:
    """The words of the table row that starts with ``name``."""
    rows = [line.split() for line in text.splitlines() if line.split()[:1] == [name]]
    assert len(rows) == 1, f"no single row {name!r} in:\n{text}"
    return rows[0]


def test_full_document() -> None:
    text = render_status(FULL)
    lines = text.splitlines()
    assert lines[0] == "SPEED_HOLD for 12.3 s  (vehicle sim, up 40.1 s)"
    assert lines[1] == "speed: set 1.50 m/s, measured 1.48 m/s"
    assert "hold-to-move: required, not held" in lines
    assert line_with(text, "E-STOP LATCHED")
    assert "  - critical input stale: scan.left" in lines
    assert "  - brake pedal pressed" in lines
    assert "  stale:board.steering: no frame for 0.3 s (for 3.2 s)" in lines
    assert "fault history: 1 cleared, latest stale:scan.right" in lines

    assert row(text, "board.steering") == ["board.steering", "12", "ms", "50", "ms", "critical"]
    assert row(text, "scan.left") == [
        "scan.left",
        "never",
        "100",
        "ms",
        "STALE",
        "critical",
    ]
    assert row(text, "scan.right")[1] == "never"  # infinite age
    assert row(text, "panel") == ["panel", "50", "ms", "200", "ms"]

    assert line_with(text, "pc104").split(maxsplit=1) == [
        "pc104",
        "counter_steer 1.50 m/s front 0.031 rad",
    ]
    assert "overrides: brake_pedal" in lines
    assert (
        "loop: 50.0 Hz, 2000 cycles, 1 overruns, jitter p99 0.80 ms, step p99 0.30 ms, "
        "wakes by timerfd, 12 deferred for a cycle"
    ) in lines
    assert line_with(text, "lms111_left").split(maxsplit=1)[1] == "backoff, 2 restart(s)"

    # The order a person reads it in: mode, speed, refusals, faults, inputs, commands,
    # loop, services.
    order = [
        "SPEED_HOLD",
        "speed:",
        "last refusal:",
        "faults (1):",
        "inputs:",
        "commands:",
        "loop:",
        "services:",
    ]
    positions = [text.index(marker) for marker in order]
    assert positions == sorted(positions)


def test_columns_of_the_inputs_table_line_up() -> None:
    _, header, *rows = render_status({"inputs": FULL["inputs"]}).splitlines()
    age_end = header.index("age") + len("age")
    limit_end = header.index("limit") + len("limit")
    for line in rows:
        words = line.split()
        age = "never" if words[1] == "never" else f"{words[1]} {words[2]}"
        limit = " ".join(words[2:4] if age == "never" else words[3:5])
        assert line.index(age, len(words[0]) + 2) + len(age) == age_end, line
        assert line.index(limit, age_end) + len(limit) == limit_end, line


def test_ready_says_whether_an_engage_press_would_be_accepted() -> None:
    blocked = render_status(
        {"mode": "ready", "engage_blockers": ["autopilot source not ready: PC104 not ready"]}
    )
    assert "engage now: would be refused:\n  - autopilot source not ready: PC104 not ready" in (
        blocked
    )
    assert "engage now: would be accepted" in render_status(
        {"mode": "ready", "engage_blockers": []}
    )
    assert "engage now" not in render_status({"mode": "engaged", "engage_blockers": []})


def test_docking_shows_the_pose_on_the_launcher_and_the_plan() -> None:
    text = render_status(
        {
            "mode": "speed_hold",
            "autopilot": {
                "source": "dock",
                "ready": True,
                "localization": {
                    "status": "ok",
                    "quality": 93,
                    "reason": "",
                    "pose": {
                        "x_m": -7.2,
                        "y_m": 0.0123,
                        "heading_deg": 0.05,
                        "sigma_x_m": 0.002,
                        "sigma_y_m": 0.003,
                        "sigma_heading_deg": 0.02,
                    },
                },
                "docking": {
                    "phase": "approach",
                    "pattern": "oblique",
                    "pattern_switches": 3,
                    "gap_m": 1.234,
                    "lateral_m": 0.0045,
                },
            },
        }
    )
    assert "localization: ok, quality 93" in text
    assert "pose on the launcher: x -7.200 m ±0.002, y +0.012 m ±0.003" in text
    assert "docking: approach, gap 1234 mm, lateral +4.5 mm, oblique (3 switches)" in text
    refused = render_status(
        {"autopilot": {"source": "dock", "refused": "outside the automatic zone: 14.0 m out"}}
    )
    assert "autopilot (dock): refuses: outside the automatic zone: 14.0 m out" in refused


def test_empty_document() -> None:
    assert render_status({}) == "UNKNOWN MODE"


def test_a_quiet_daemon_says_none_where_it_reported_nothing() -> None:
    text = render_status({"mode": "ready", "faults": [], "overrides": {"steering": False}})
    assert text.splitlines() == ["READY", "faults: none", "overrides: none"]


@pytest.mark.parametrize(
    "doc",
    [
        {"mode": 5, "mode_since_s": "long", "uptime_s": [1]},
        {"mode": None, "set_speed_mps": "fast", "measured_speed_mps": True},
        {"hold_to_move": 3, "estop_latched": "yes", "last_refusal": "one reason"},
        {"faults": "none at all", "fault_history": {"a": 1}},
        {"faults": [None, 3, {"since_s": "x"}, {"key": {"nested": [1, 2]}}]},
        {"inputs": [1, 2], "commands": "x", "overrides": [True], "services": None},
        {"inputs": {"a": 5, "b": {"age_s": True, "limit_s": "x"}, "c": {"age_s": -1e308}}},
        {"inputs": {"": {}}, "commands": {"": None}, "services": {"x" * 500: "y" * 500}},
        {"loop": {"rate_hz": "fast", "cycles": 10**400, "overruns": float("nan")}},
        {"loop": [1], "mode_since_s": float("inf"), "uptime_s": -5.0, "vehicle": {"x": 1}},
        {"mode": "\x1b[2J\x07ready\nnow", "last_refusal": ["\x1b[31mred\x1b[0m"]},
        {(1, 2): "tuple key", 3: 4, "commands": {(1,): object()}},
    ],
)
def test_garbage_is_rendered_without_crashing(doc: dict[str, Any]) -> None:
    text = render_status(doc)
    assert text.splitlines()[0]
    assert "\x1b" not in text and "\x07" not in text  # no terminal control from the daemon
    assert all(len(line) < 400 for line in text.splitlines())


def test_unreadable_faults_are_not_shown_as_none() -> None:
    assert "faults: unreadable" in render_status({"faults": "oops"})
    assert row(render_status({"inputs": {"a": 5}}), "a")[1] == "?"


def test_not_even_a_dict() -> None:
    assert render_status([1, 2]) == "UNKNOWN MODE"  # type: ignore[arg-type]


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=10), children, max_size=4)
    ),
    max_leaves=20,
)
KEYS = st.sampled_from(sorted(FULL)) | st.text(max_size=10)


def printable(text: str) -> bool:
    return all(ch.isprintable() for line in text.split("\n") for ch in line)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(KEYS, JSON, max_size=8))
def test_any_json_document_renders_as_printable_lines(doc: dict[str, Any]) -> None:
    text = render_status(doc)
    assert text.split("\n")[0]
    assert printable(text)


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(sorted(FULL)), JSON)
def test_any_value_in_any_slot_of_a_full_document_renders(key: str, value: Any) -> None:
    text = render_status({**FULL, key: value})
    assert printable(text)
    if key != "mode":
        assert text.startswith("SPEED_HOLD")


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (0.012, "12 ms"),
        (0.0, "0 ms"),
        (12.34, "12.3 s"),
        (119.9, "119.9 s"),
        (125.0, "2 min 5 s"),
        (7300.0, "2 h 1 min"),
        (math.inf, "never"),
        (math.nan, "never"),
    ],
)
def test_format_duration(seconds: float, text: str) -> None:
    assert format_duration(seconds) == text


def test_a_pedals_vehicle_shows_its_speed_controller_and_its_links() -> None:
    doc = {
        "mode": "speed_hold",
        "pedal_speed": {"state": "drive", "reason": "", "reference_speed_mps": 2.5},
        "links": {
            "gnss": "up 10.0 epochs/s, bad lines 2",
            "board.throttle": "up 50 fps, crc=0 reconnects=0 lease_expired=0",
        },
    }
    text = render_status(doc)
    assert "pedals: drive, reference 2.50 m/s" in text.splitlines()
    assert line_with(text, "gnss").split(maxsplit=1) == ["gnss", "up 10.0 epochs/s, bad lines 2"]
    braking = dict(doc, pedal_speed={"state": "stop", "reason": "stop requested"})
    assert "pedals: stop (stop requested)" in render_status(braking).splitlines()


def test_an_armed_pedal_sweep_shows_its_phase_run_and_pedals() -> None:
    doc = {
        "mode": "speed_hold",
        "pedal_sweep": {
            "phase": "throttle",
            "run": 2,
            "runs": 6,
            "throttle_pct": 30.0,
            "brake_pct": 0.0,
        },
    }
    assert (
        "pedal sweep: throttle, run 2/6, throttle 30 %, brake 0 %"
        in render_status(doc).splitlines()
    )
    odd = {"mode": "ready", "pedal_sweep": {"phase": "x\x1b[2J", "run": "2", "brake_pct": None}}
    line = line_with(render_status(odd), "pedal sweep")
    assert "\x1b" not in line and "run" not in line


def test_the_armed_palm_tree_shows_its_phase_arc_wheel_and_a_stuck_wheel() -> None:
    palm = {"phase": "drive", "arc": 3, "arcs": 7, "wheel_target_rad": 3.1416, "driven_m": 4.25}
    doc = {"mode": "speed_hold", "palm_tree": palm}
    assert (
        "palm tree: drive, arc 3/7, wheel +3.14 rad, 4.2 m driven"
        in render_status(doc).splitlines()
    )
    stuck = {"phase": "steer", "stuck": "the wheel is at +1.00 rad\x1b[2J"}
    line = line_with(render_status({"mode": "engaged", "palm_tree": stuck}), "palm tree")
    assert "STUCK: the wheel is at +1.00 rad" in line and "\x1b" not in line
    assert "arc" not in line.split("STUCK")[0]


def test_armed_look_ahead_runs_and_the_servo_torque_flag_show() -> None:
    doc = {
        "mode": "speed_hold",
        "autopilot": {
            "source": "route",
            "tuning": {
                "phase": "test",
                "run": 2,
                "runs": 36,
                "describe": "line +3 m at 4.47 m/s, look-ahead 0.5 + 0.6 s x v (min 1.5 m)",
                "test_left_s": 12.4,
                "stopping": False,
            },
        },
        "servo_torque": {"retune": True, "change_pct": -22.0, "reason": "the wheel needs less"},
    }
    lines = render_status(doc).splitlines()
    assert (
        "look-ahead runs: test, run 3/36 (line +3 m at 4.47 m/s, look-ahead 0.5 + 0.6 s x v "
        "(min 1.5 m)), 12 s of test left"
    ) in lines
    assert line_with(render_status(doc), "servo torque").startswith("servo torque: CHANGED")
    calm = dict(doc, servo_torque={"retune": False, "change_pct": 3.0, "reason": ""})
    assert "servo torque: as tuned (+3 %)" in render_status(calm).splitlines()
    odd = dict(doc, autopilot={"tuning": {"phase": 5, "run": "x", "describe": "\x1b[2J"}})
    line = line_with(render_status(odd), "look-ahead runs")
    assert "\x1b" not in line and "run " not in line


def test_the_pallet_source_shows_the_pose_on_the_posts_the_target_and_the_approach() -> None:
    pilot = {
        "source": "pallet",
        "localization": {
            "status": "ok",
            "reason": "",
            "landmarks": ["landmark_1", "landmark_5"],
            "pose": {"x_m": 0.91, "y_m": -2.5, "yaw_deg": 0.12},
        },
        "merged": True,
        "target": "row_a.r0c1",
        "phase": "final",
        "approach": {"lateral_mm": 2.5, "heading_deg": -0.08, "distance_m": 0.42},
    }
    text = render_status({"mode": "speed_hold", "autopilot": pilot})
    assert "pose on the posts: x +0.910 m, y -2.500 m, heading +0.12 deg" in text
    assert "(landmark_1, landmark_5)" in text
    assert "pallet: row_a.r0c1, final, 0.42 m to go, lateral +2.5 mm, heading -0.08 deg" in text
    waiting = render_status(
        {"autopilot": {"source": "pallet", "merged": False, "refused": "the maps are not merged"}}
    )
    assert "pallet: none selected (maps not merged)" in waiting
    assert "autopilot (pallet): refuses: the maps are not merged" in waiting
