"""The journal's JSON lines are strict JSON, whatever a log call passes."""

from __future__ import annotations

import io
import json
import math
from typing import Any

from hypothesis import given
from hypothesis import strategies as st

from appliance.logs import configure_logging, get_logger


def strict(text: str) -> Any:
    """``json.loads`` without Python's extension: a bare NaN or Infinity is an error."""

    def refuse(constant: str) -> None:
        raise ValueError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


def logged(**fields: Any) -> dict[str, Any]:
    stream = io.StringIO()
    configure_logging("debug", stream=stream, json=True)
    get_logger("test").warning("something", **fields)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 1, lines
    document = strict(lines[0])
    assert isinstance(document, dict)
    return document


def test_a_device_never_heard_from_logs_its_infinite_age_as_a_string() -> None:
    document = logged(age_s=round(math.inf, 3), limit_s=0.1, spread=-math.inf, fit=math.nan)
    assert document["age_s"] == "Infinity" and float(document["age_s"]) == math.inf
    assert document["spread"] == "-Infinity" and math.isnan(float(document["fit"]))
    assert document["limit_s"] == 0.1 and document["event"] == "something"


def test_finite_events_are_written_as_before() -> None:
    document = logged(age_s=0.25, count=3, name="steering", nested={"a": [1.5, None, True]})
    assert document["age_s"] == 0.25 and document["count"] == 3
    assert document["nested"] == {"a": [1.5, None, True]}


values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.tuples(inner, inner)
        | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)


def same(value: Any, back: Any) -> bool:
    """Whether ``back`` is ``value`` as the journal has it: tuples as lists, a
    non-finite float as its name in a string."""
    if isinstance(value, float) and not math.isfinite(value):
        return isinstance(back, str) and (
            math.isnan(float(back)) if math.isnan(value) else float(back) == value
        )
    if isinstance(value, list | tuple):
        return isinstance(back, list) and len(back) == len(value) and all(map(same, value, back))
    if isinstance(value, dict):
        return (
            isinstance(back, dict)
            and back.keys() == value.keys()
            and all(same(value[key], back[key]) for key in value)
        )
    return bool(back == value and type(back) is type(value))


@given(values)
def test_any_value_is_strict_json_and_reads_back(value: Any) -> None:
    assert same(value, logged(value=value)["value"])
