"""The compiled codec against the reference: the same JSON out, the same objects back, the
same refusals, on real objects, on arbitrary JSON and on damaged real encodings."""

from __future__ import annotations

import copy
import json
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.core.inputs import ControlInputs
from appliance.recording.codec import CodecError, decode, encode
from appliance.recording.fastcodec import encode_fast
from appliance.recording.fastdecode import decode_fast
from drivers.lms111.mounted import MountedScan
from tests.unit.recording.test_codec import (
    DECLARED,
    GNSS_POSE,
    JSON,
    PATHS,
    VALID,
    _inputs,
    _scans,
)


def _same_outcome(data: Any, declared: Any) -> None:
    """Both decode to objects that encode identically (by both encoders), or both refuse."""
    try:
        reference: Any = decode(data, declared)
    except CodecError:
        reference = CodecError
    try:
        fast: Any = decode_fast(data, declared)
    except CodecError:
        fast = CodecError
    if reference is CodecError or fast is CodecError:
        assert reference is fast, (reference, fast)
        return
    text = json.dumps(encode(reference, declared), sort_keys=True)
    assert json.dumps(encode_fast(fast, declared), sort_keys=True) == text
    assert json.dumps(encode(fast, declared), sort_keys=True) == text


def test_real_objects_encode_to_the_same_json() -> None:
    inputs = _inputs(GNSS_POSE)
    assert json.dumps(encode_fast(inputs, ControlInputs)) == json.dumps(
        encode(inputs, ControlInputs)
    )
    for scan in _scans().values():
        if scan is not None:
            assert encode_fast(scan, MountedScan) == encode(scan, MountedScan)
    for encoded, declared in VALID:
        _same_outcome(encoded, declared)


@settings(max_examples=100, deadline=None)
@given(JSON, st.sampled_from(DECLARED))
def test_arbitrary_json_gets_the_same_verdict(data: Any, declared: Any) -> None:
    _same_outcome(data, declared)


@settings(max_examples=150, deadline=None)
@given(st.data(), JSON, st.booleans())
def test_damaged_real_encodings_get_the_same_verdict(
    data: st.DataObject, replacement: Any, remove: bool
) -> None:
    which = data.draw(st.sampled_from(range(len(VALID))))
    encoded, declared = VALID[which]
    path = data.draw(st.sampled_from(PATHS[which]))
    damaged = copy.deepcopy(encoded)
    if not path:
        damaged = replacement
    else:
        parent = damaged
        for key in path[:-1]:
            parent = parent[key]
        if remove and isinstance(parent, dict):
            del parent[path[-1]]
        else:
            parent[path[-1]] = replacement
    _same_outcome(damaged, declared)


@settings(max_examples=60, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([float, float | None]))
def test_floats_encode_alike(value: float, declared: Any) -> None:
    assert json.dumps(encode_fast(value, declared)) == json.dumps(encode(value, declared))


def test_values_of_the_wrong_type_are_refused_by_both() -> None:
    for value, declared in ((True, float), ("1", int), (1.5, int), (None, float), ((1,), list)):
        refused = []
        for encoder in (encode, encode_fast):
            try:
                encoder(value, declared)
            except CodecError:
                refused.append(encoder)
        assert len(refused) == 2, (value, declared, refused)
