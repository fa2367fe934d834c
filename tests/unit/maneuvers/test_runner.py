"""The runner against a fake daemon: what it asks, in which order, and why it stops.

The fake answers as the control socket does (``status``, ``maneuver``, ``samples``) and
records every call, so the tests see that the preconditions are checked again after the
technician's answer (which can take longer than an idle connection lives), that the tap
is always stopped, and what a refusal says.
"""

from __future__ import annotations

import asyncio
import io
from pathlib import Path
from typing import Any

import pytest

from appliance.config import load_config
from appliance.maneuvers.pot_map_step import PotMapStep
from appliance.maneuvers.runner import ManeuverRunner, RefusedError
from appliance.maneuvers.samples_file import SamplesWriter, header, read_samples_file
from appliance.maneuvers.steps import StepContext
from tests.unit.maneuvers.test_steps import tap_samples

CONFIG = load_config("husky")
CONTEXT = StepContext(CONFIG, None, {"x_steering_ratio": 18.0})
FRESH = {"age_s": 0.01, "stale": False}


class FakeDaemon:
    def __init__(self, samples: list[dict[str, Any]], per_reply: int = 200) -> None:
        self.calls: list[str] = []
        self.samples = samples
        self.per_reply = per_reply
        self.stopped = False
        self.mode = "ready"
        self.closed = 0

    def status_doc(self) -> dict[str, Any]:
        return {
            "vehicle": CONFIG.name,
            "mode": self.mode,
            "faults": [],
            "measured_speed_mps": 0.0,
            "inputs": {"board.steering": FRESH, "steering.pot": FRESH},
            "maneuver": {"step": "pot-map", "active": False, "first_seq": 0},
        }

    async def status(self) -> dict[str, Any]:
        self.calls.append("status")
        return {"ok": True, "status": self.status_doc()}

    async def call(self, request: dict[str, Any]) -> dict[str, Any]:
        self.calls.append(f"{request['op']}:{request.get('action', request.get('since'))}")
        if request["op"] == "maneuver":
            self.stopped = request["action"] == "stop"
            return {"ok": True, "accepted": True, "message": "ok"}
        since = int(request["since"])
        chunk = self.samples[since : since + self.per_reply]
        return {
            "ok": True,
            "samples": chunk,
            "next": since + len(chunk),
            "missed": 0,
            "active": not self.stopped,
        }

    async def close(self) -> None:
        self.closed += 1


def runner(daemon: FakeDaemon, tmp_path: Path, confirm: Any) -> ManeuverRunner:
    writer = SamplesWriter(tmp_path / "s.jsonl", header("pot-map", CONFIG.name, "0", "x"))
    return ManeuverRunner(
        PotMapStep(CONTEXT),
        daemon,
        writer,
        io.StringIO(),
        timeout_s=60.0,  # type: ignore[arg-type]
        confirm=confirm,
    )


def test_the_checks_run_again_after_the_answer_and_the_tap_is_stopped(tmp_path: Path) -> None:
    daemon = FakeDaemon(tap_samples())
    outcome = asyncio.run(runner(daemon, tmp_path, lambda _q: True).run())
    assert outcome.complete and outcome.reason == "complete", outcome
    assert daemon.calls[:3] == ["status", "status", "maneuver:start"]
    assert daemon.closed == 1 and "maneuver:stop" in daemon.calls


def test_what_the_tap_took_before_its_stop_is_in_the_file(tmp_path: Path) -> None:
    # The daemon's tap goes on until the stop reaches it: the samples between the last
    # poll and the stop are fetched after it, so the file is what the flight recording
    # replays (the runtime tests compare the two).
    samples = tap_samples()
    late = [{**samples[-1], "seq": len(samples) + i} for i in range(120)]
    daemon = FakeDaemon(samples + late, per_reply=50)
    outcome = asyncio.run(runner(daemon, tmp_path, lambda _q: True).run())
    assert outcome.complete, outcome
    stop = daemon.calls.index("maneuver:stop")
    after = daemon.calls[stop + 1 :]
    assert after and all(call.startswith("samples:") for call in after)
    assert after[-1] == f"samples:{len(samples) + len(late)}"  # drained to the end
    written = read_samples_file(tmp_path / "s.jsonl", CONFIG.name)
    assert [s["seq"] for s in written.samples] == list(range(len(samples) + len(late)))
    assert outcome.samples == len(samples) + len(late)


def test_a_change_while_the_technician_answers_refuses_the_start(tmp_path: Path) -> None:
    daemon = FakeDaemon(tap_samples())

    def engage_meanwhile(_question: str) -> bool:
        daemon.mode = "engaged"
        return True

    with pytest.raises(RefusedError, match="ENGAGED"):
        asyncio.run(runner(daemon, tmp_path, engage_meanwhile).run())
    assert "maneuver:start" not in daemon.calls


def test_no_confirmation_no_start(tmp_path: Path) -> None:
    daemon = FakeDaemon(tap_samples())
    with pytest.raises(RefusedError, match="not confirmed"):
        asyncio.run(runner(daemon, tmp_path, lambda _q: False).run())
    assert daemon.calls == ["status"]


class NeverStops(FakeDaemon):
    """A tap the stop does not end (another step's): it keeps taking samples."""

    async def call(self, request: dict[str, Any]) -> dict[str, Any]:
        reply = await super().call(request)
        self.stopped = False
        if request["op"] == "samples":  # one more sample taken since every poll
            self.samples.append({**self.samples[-1], "seq": len(self.samples)})
        return reply


def test_a_tap_that_goes_on_after_the_stop_is_not_chased(tmp_path: Path) -> None:
    daemon = NeverStops(tap_samples(), per_reply=50)
    outcome = asyncio.run(runner(daemon, tmp_path, lambda _q: True).run())
    assert outcome.complete, outcome
    stop = daemon.calls.index("maneuver:stop")
    assert len(daemon.calls) - stop - 1 == 1  # one poll after the stop, then done


def test_an_abort_mid_batch_writes_every_sample_once(tmp_path: Path) -> None:
    # The e-stop in the middle of a reply: the run ends there, the rest of that reply and
    # what came after are fetched after the stop, and no sample is written twice.
    samples = tap_samples()[:120]
    samples[70] = {**samples[70], "mode": "estop"}
    daemon = FakeDaemon(samples, per_reply=50)
    outcome = asyncio.run(runner(daemon, tmp_path, lambda _q: True).run())
    assert not outcome.complete and "ESTOP" in outcome.reason, outcome
    written = read_samples_file(tmp_path / "s.jsonl", CONFIG.name)
    assert [s["seq"] for s in written.samples] == list(range(120))
    assert outcome.samples == 120
