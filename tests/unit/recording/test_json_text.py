"""`json_text.loads` is `json.loads`: the same values to the bit and the same types, or the
same refusal, on any JSON the codec writes and on text that is damaged or odd."""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.recording.json_text import loads

SCALARS = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=-(10**60), max_value=10**60)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.floats(min_value=-1e-300, max_value=1e-300)  # subnormals and their neighbours
    | st.text()
)
VALUES = st.recursive(
    SCALARS,
    lambda children: (
        st.lists(children, max_size=6) | st.dictionaries(st.text(max_size=8), children, max_size=6)
    ),
    max_leaves=40,
)


def identical(a: Any, b: Any) -> bool:
    """Equal, of the same types all the way down, floats to the bit, keys in order."""
    if type(a) is not type(b) or isinstance(a, type):
        return a is b
        return False
    if isinstance(a, float):
        return struct.pack("<d", a) == struct.pack("<d", b)
    if isinstance(a, list):
        return len(a) == len(b) and all(identical(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict):
        return list(a) == list(b) and all(identical(a[k], b[k]) for k in a)
    return bool(a == b)


def outcome(parse: Callable[[bytes | str], Any], text: bytes | str) -> Any:
    """What ``parse`` makes of ``text``: its value, or the type of its refusal."""
    try:
        return parse(text)
    except ValueError as exc:
        return type(exc)


def same_outcome(text: bytes | str) -> None:
    assert identical(outcome(loads, text), outcome(json.loads, text)), text


@given(VALUES, st.booleans())
@settings(max_examples=400, deadline=None)
def test_any_json_value_parses_identically(value: Any, ascii_only: bool) -> None:
    text = json.dumps(value, ensure_ascii=ascii_only)
    same_outcome(text)
    same_outcome(text.encode("utf-8", "surrogatepass"))
    compact = json.dumps(value, separators=(",", ":"), ensure_ascii=ascii_only)
    same_outcome(compact.encode("utf-8", "surrogatepass"))


@given(VALUES, st.data())
@settings(max_examples=300, deadline=None)
def test_damaged_json_is_refused_or_parsed_identically(value: Any, data: st.DataObject) -> None:
    text = json.dumps(value).encode()
    at = data.draw(st.integers(min_value=0, max_value=len(text)))
    insert = data.draw(
        st.sampled_from([b"", b"-", b"0", b".", b"e", b"\\", b'"', b",", b"]", b"}", b"\xff"])
    )
    cut = data.draw(st.integers(min_value=0, max_value=2))
    same_outcome(text[:at] + insert + text[at + cut :])


@pytest.mark.parametrize(
    "text",
    [
        "NaN",
        "Infinity",
        "-Infinity",
        '{"a": NaN, "b": [Infinity, -Infinity]}',
        "-NaN",
        "nan",
        "inf",
        '"nan"',
        "1e400",
        "-1e400",
        "1e-400",
        "-0",
        "-0.0",
        "4.9e-324",
        "2.4703282292062328e-324",
        "1.7976931348623158e308",
        "9007199254740993",
        "1" + "0" * 4299,
        "1" + "0" * 4300,  # past Python's digit limit: json.loads refuses, and so does this
        '{"a": 1, "b": 2, "a": 3}',
        '"\\ud800"',
        '"\\udfff x"',
        '"\\ud83d\\ude00"',
        '"a\\u0000b"',
        '"a\tb"',
        "\ufeff{}",
        "[1,]",
        "01",
        "1.",
        " [1] ",
        "[1] x",
        "[" * 300 + "]" * 300,  # deeper than from_json goes: json.loads answers
    ],
)
def test_corners_parse_identically(text: str) -> None:
    same_outcome(text)
    same_outcome(text.encode("utf-8", "surrogatepass"))


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16", "utf-32"])
def test_what_json_loads_decodes_from_bytes_parses_identically(encoding: str) -> None:
    same_outcome('{"x": [1.5, "é", null]}'.encode(encoding))


def test_non_finite_numbers_are_floats_as_json_loads_makes_them() -> None:
    value = loads(b'[NaN, Infinity, -Infinity, "inf"]')
    assert math.isnan(value[0]) and value[1:3] == [math.inf, -math.inf]
    assert value[3] == "inf"  # the codec's own spelling stays a string for it to decode
