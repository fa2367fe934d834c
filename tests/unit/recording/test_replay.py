"""Replay's comparison of outputs, on cycles recorded here by a core and the recorder's
own encoder: an output written byte for byte as replay makes it matches, one written
another way (key order, spacing) still matches by value, and one changed anywhere is a
divergence that names the field, both values and the time."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import pytest

from appliance.config import load_config
from appliance.core.core import ControlCore
from appliance.recording.channels import CYCLE_TOPIC, encode_cycle, encode_reset
from appliance.recording.reader import RecordedMessage
from appliance.recording.replay import Replayer
from tests.unit.core.vehicle import BenchVehicle

CONFIG = load_config("sim")
CYCLES = 40
PERIOD_NS = 20_000_000


def _recording() -> list[RecordedMessage]:
    """A core started and stepped on a vehicle at rest, as the recorder writes it."""
    core = ControlCore(CONFIG, None)
    vehicle = BenchVehicle()
    core.reset()
    messages = [_message(encode_reset(0.0), 0)]
    for k in range(1, CYCLES + 1):
        now_s = k * PERIOD_NS / 1e9
        inputs = vehicle.inputs(dict(core.staleness.age_limits_s))
        output = core.step(inputs, now_s)
        messages.append(_message(encode_cycle(k * PERIOD_NS, now_s, inputs, {}, output), k))
    return messages


def _message(encoded: Any, k: int) -> RecordedMessage:
    first = next(iter(encoded))
    return RecordedMessage(first.spec.topic, first.spec.schema_name, k * PERIOD_NS, k, first.data)


def _rewritten(
    message: RecordedMessage, change: Callable[[dict[str, Any]], bytes]
) -> RecordedMessage:
    return RecordedMessage(
        message.topic,
        message.schema,
        message.log_time_ns,
        message.sequence,
        change(json.loads(message.data)),
    )


def _replay(messages: list[RecordedMessage]) -> Replayer:
    replayer = Replayer(ControlCore(CONFIG, None))
    replayer.feed(messages)
    return replayer


@pytest.fixture(scope="module")
def recording() -> list[RecordedMessage]:
    return _recording()


def test_the_recorders_bytes_match(recording: list[RecordedMessage]) -> None:
    result = _replay(recording).result
    assert result.cycles == CYCLES and result.resets == 1
    assert result.divergent_cycles == 0 and result.matched


def test_an_output_written_another_way_matches_by_value(
    recording: list[RecordedMessage],
) -> None:
    """Sorted keys and spaces: not the bytes replay writes, the same values."""
    rewritten = [
        _rewritten(m, lambda data: json.dumps(data, sort_keys=True, indent=1).encode())
        if m.topic == CYCLE_TOPIC
        else m
        for m in recording
    ]
    assert rewritten[-1].data != recording[-1].data
    result = _replay(rewritten).result
    assert result.cycles == CYCLES and result.divergent_cycles == 0


def test_a_changed_output_is_a_divergence_that_names_the_field(
    recording: list[RecordedMessage],
) -> None:
    at = 25

    def nudged(data: dict[str, Any]) -> bytes:
        data["output"]["now_s"] += 1e-9
        return json.dumps(data, separators=(",", ":")).encode()

    changed = [*recording[:at], _rewritten(recording[at], nudged), *recording[at + 1 :]]
    result = _replay(changed).result
    assert result.divergent_cycles == 1
    (divergence,) = result.divergences
    assert divergence.field == "output.now_s"
    assert divergence.log_time_ns == at * PERIOD_NS
    assert divergence.recorded == divergence.replayed + 1e-9
