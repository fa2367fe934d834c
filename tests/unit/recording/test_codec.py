"""The recording's JSON codec: real inputs and outputs of the core come back as the very
objects (types, floats bit for bit, raw scanner arrays), through real JSON text, and
anything that does not fit its declared type is a `CodecError`, never another exception.

Sameness is judged by a walk over the objects written here (`_assert_same`), not by the
codec's own output, and floats by their IEEE bytes (``struct.pack``)."""

from __future__ import annotations

import base64
import copy
import dataclasses
import json
import math
import struct
import tracemalloc
from collections.abc import Mapping
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from appliance.config import load_config
from appliance.core.core import ControlCore
from appliance.core.inputs import ControlInputs, LinkCounts
from appliance.core.output import CoreOutput
from appliance.localization.gnss_pose import GnssNoFix, GnssPose, HeadingSource, SigmaSource
from appliance.recording.codec import CodecError, decode, encode
from drivers.geometry import Pose2D
from drivers.gnss.sentences import FixQuality
from drivers.lms111.mounted import MountedScan
from drivers.lms111.scan import Encoder, ScanTimestamp, scan_from_ranges
from drivers.pc104.messages import HlExpectedPose, HlPose, PoseState
from tests.unit.core.vehicle import BenchVehicle

CONFIG = load_config("flatbed")
PROPERTY = settings(max_examples=60, deadline=None)


# ---- an independent sameness -----------------------------------------------------------


def _float_bits(value: float) -> bytes:
    return struct.pack("<d", value)


def _assert_same(a: Any, b: Any, where: str = "$") -> None:
    """``b`` is ``a`` rebuilt: same types all the way down, floats bit for bit (nan: nan),
    arrays of the same dtype, shape and bytes, and read-only."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} became {type(b).__name__}"
    if isinstance(a, float):
        if math.isnan(a):
            assert math.isnan(b), f"{where}: nan became {b!r}"
        else:
            assert _float_bits(a) == _float_bits(b), f"{where}: {a!r} became {b!r}"
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape) == (b.dtype, b.shape), where
        assert a.tobytes() == b.tobytes(), f"{where}: array values differ"
        assert not b.flags.writeable, f"{where}: a decoded array is writeable"
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            if f.init:
                _assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, Mapping):
        assert list(a) == list(b), f"{where}: keys {list(a)} became {list(b)}"
        for key in a:
            _assert_same(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, tuple | list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} became {b!r}"


def _round_trip(value: Any, declared: Any) -> Any:
    """encode → JSON text → decode → encode again: the same text, and the object back."""
    text = json.dumps(encode(value, declared), allow_nan=False)  # no bare NaN for Foxglove
    back = decode(json.loads(text), declared)
    assert json.dumps(encode(back, declared), allow_nan=False) == text
    _assert_same(value, back)
    return back


# ---- real objects --------------------------------------------------------------------------


def _scans() -> dict[str, MountedScan | None]:
    rng = np.random.default_rng(7)
    ranges = rng.uniform(0.5, 70.0, 541)  # past 65.535 m: the scale factor 2 path
    ranges[::13] = 0.0  # no echo
    left_scan = scan_from_ranges(
        ranges, angular_step_deg=0.5, intensities=rng.integers(0, 4000, 541)
    )
    left_scan = dataclasses.replace(
        left_scan,
        scan_counter=41,
        device_time_us=0xFFFF_FFF0,
        encoders=(Encoder(123, -4),),
        device_name="LMS111 left",
        timestamp=ScanTimestamp(2024, 2, 29, 23, 59, 59, 999_999),
        host_receive_time_s=-0.0,
    )
    right_scan = scan_from_ranges(rng.uniform(0.5, 20.0, 1081), angular_step_deg=0.25)
    return {
        "left": MountedScan(left_scan, "left", Pose2D(3.25, 1.1, 0.7853981633974483), 12.5, 7),
        "right": MountedScan(right_scan, "right", Pose2D(3.25, -1.1, -0.0), 12.51, 2**40),
        "rear": None,
    }


GNSS_POSE = GnssPose(
    measurement_time_s=1234.5678901234,
    utc_time_of_day_s=86399.99,
    east_m=-0.0,
    north_m=1e-310,  # subnormal
    up_m=-12.25,
    quality=FixQuality.RTK_FIXED,
    satellites=None,
    hdop=math.inf,
    yaw_rad=-math.pi,
    heading_source=HeadingSource.TRUE_HEADING,
    course_yaw_rad=None,
    speed_mps=math.nan,
    yaw_rate_rad_per_s=-math.inf,
    sigma_east_m=0.1 + 0.2,
    sigma_north_m=None,
    sigma_worst_m=5e-324,
    sigma_source=SigmaSource.GST,
)


def _inputs(gnss: GnssPose | GnssNoFix | None) -> ControlInputs:
    core = ControlCore(CONFIG, None)
    bench = BenchVehicle().inputs(dict(core.staleness.age_limits_s))
    assert bench.throttle is not None
    ages = {**bench.ages_s, "gnss": math.inf, "scan.rear": math.nan, "odd": -0.0}
    return dataclasses.replace(
        bench,
        ages_s=ages,
        throttle=dataclasses.replace(bench.throttle, pedal_position_pct=-0.0),
        pc104_link=LinkCounts(errors=3, good=2**53 + 1),
        scans=_scans(),
        service_faults={"gnss-input": "failed: exit 1"},
        gnss=gnss,
        gnss_seq=9,
    )


def test_control_inputs_with_two_scans_and_a_fix_come_back_whole() -> None:
    inputs = _inputs(GNSS_POSE)
    back = _round_trip(inputs, ControlInputs)
    assert isinstance(back.gnss, GnssPose)
    assert math.copysign(1.0, back.gnss.east_m) == -1.0  # -0.0 stays -0.0
    assert back.throttle is not None
    assert math.copysign(1.0, back.throttle.pedal_position_pct) == -1.0  # in `float | None`
    left = back.scans["left"]
    assert left is not None and left.scan.channel("RSSI1") is not None
    # the SI views are computed again from the raw data, identically
    original = inputs.scans["left"]
    assert original is not None
    assert left.scan.ranges_m.tobytes() == original.scan.ranges_m.tobytes()
    assert left.angles_vehicle_rad.tobytes() == original.angles_vehicle_rad.tobytes()


def test_the_gnss_union_says_which_arm_it_holds() -> None:
    for gnss in (GNSS_POSE, GnssNoFix(-0.0, "GGA quality 0")):
        encoded = encode(_inputs(gnss), ControlInputs)
        assert encoded["gnss"]["_type"] == type(gnss).__name__
        back = _round_trip(_inputs(gnss), ControlInputs)
        assert type(back.gnss) is type(gnss)
    assert encode(_inputs(None), ControlInputs)["gnss"] is None


def test_a_core_output_comes_back_whole() -> None:
    core = ControlCore(CONFIG, None)
    output = core.step(_inputs(GNSS_POSE), 1.0)
    assert output.notes  # BOOT → SELF_CHECK: a note with free-form fields
    _round_trip(output, CoreOutput)
    posed = dataclasses.replace(
        output,
        steer_tyre_rad=-0.0,
        speed_setpoint_mps=math.inf,
        pc104_pose=HlPose(1.5, -2.5, -0.0, PoseState.DEGRADED),
        pc104_expected_pose=HlExpectedPose(math.nan, 0.1, 3.0),
    )
    back = _round_trip(posed, CoreOutput)
    assert back.pc104_pose.state is PoseState.DEGRADED


def test_non_finite_floats_are_strings_and_the_json_is_strict() -> None:
    encoded = encode(GNSS_POSE, GnssPose)
    assert (encoded["hdop"], encoded["yaw_rate_rad_per_s"], encoded["speed_mps"]) == (
        "inf",
        "-inf",
        "nan",
    )
    assert json.loads(json.dumps(encoded))["east_m"] == 0.0  # a number, signed below
    assert json.dumps(encoded["east_m"]) == "-0.0"


# ---- properties ------------------------------------------------------------------------------

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)


@PROPERTY
@given(ANY_FLOAT, ANY_FLOAT)
def test_any_float_in_a_float_field_comes_back_bit_for_bit(x: float, y: float) -> None:
    for value, declared in ((x, float), (x, float | None), (GnssNoFix(x, "r"), GnssNoFix)):
        back = decode(json.loads(json.dumps(encode(value, declared), allow_nan=False)), declared)
        got = back.measurement_time_s if isinstance(back, GnssNoFix) else back
        if math.isnan(x):
            assert math.isnan(got)
        else:
            assert _float_bits(got) == _float_bits(x)
            assert math.copysign(1.0, got) == math.copysign(1.0, x)
    pose = _round_trip(Pose2D(x, y, -x), Pose2D)
    assert type(pose) is Pose2D


ARRAY_DTYPES = st.sampled_from(
    [
        np.uint8,
        np.int8,
        np.uint16,
        np.int16,
        np.uint32,
        np.int32,
        np.int64,
        np.float32,
        np.float64,
        np.bool_,
    ]
)


@PROPERTY
@given(hnp.arrays(ARRAY_DTYPES, hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5)))
def test_every_array_the_encoder_writes_comes_back_identical(array: np.ndarray) -> None:
    back = decode(json.loads(json.dumps(encode(array, np.ndarray))), np.ndarray)
    _assert_same(array, back)


def test_a_big_endian_array_comes_back_native_with_its_values() -> None:
    array = np.array([1.5, -0.0, math.inf, 2.0**-1074], dtype=">f8")
    encoded = encode(array, np.ndarray)
    assert encoded["dtype"] == "<f8"
    back = decode(encoded, np.ndarray)
    assert back.dtype == np.float64 and back.dtype.isnative
    assert [_float_bits(v) for v in back.tolist()] == [_float_bits(v) for v in array.tolist()]


JSON_LEAVES = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=-(2**70), max_value=2**1100)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=6)
    | st.sampled_from(["inf", "-inf", "nan", "<u2", "|V8", "GnssPose", "GnssNoFix", "AAAA"])
)
JSON_KEYS = st.text(max_size=6) | st.sampled_from(
    ["_type", "dtype", "shape", "b64", "scan", "sensor", "ages_s", "mode", "now_s", "reason"]
)
JSON = st.recursive(
    JSON_LEAVES,
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(JSON_KEYS, children, max_size=4)
    ),
    max_leaves=16,
)
DECLARED: list[Any] = [
    ControlInputs,
    MountedScan,
    CoreOutput,
    float,
    tuple[int, int],
    GnssPose | GnssNoFix | None,
    np.ndarray,
]


def _decodes_or_refuses(data: Any, declared: Any) -> None:
    """Either an object that encodes back to a fixed point, or a CodecError."""
    refusal: str | None
    try:
        value = decode(data, declared)
    except CodecError as exc:
        refusal = str(exc)
    else:
        refusal = None
    if refusal is not None:
        assert refusal  # a message that says something
        return
    again = encode(value, declared)
    _assert_same(value, decode(json.loads(json.dumps(again)), declared))


@settings(max_examples=100, deadline=None)
@given(JSON, st.sampled_from(DECLARED))
def test_arbitrary_json_decodes_or_is_refused_with_a_codec_error(data: Any, declared: Any) -> None:
    _decodes_or_refuses(data, declared)


def _valid_encodings() -> list[tuple[Any, Any]]:
    core = ControlCore(CONFIG, None)
    inputs = _inputs(GNSS_POSE)
    return [
        (encode(inputs, ControlInputs), ControlInputs),
        (encode(_inputs(GnssNoFix(1.0, "none")), ControlInputs), ControlInputs),
        (encode(core.step(inputs, 1.0), CoreOutput), CoreOutput),
    ]


VALID = _valid_encodings()


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """The path (keys and indexes) to every part of a JSON value, the value itself first."""
    paths = [prefix]
    items = (
        node.items()
        if isinstance(node, dict)
        else enumerate(node)
        if isinstance(node, list)
        else ()
    )
    for key, child in items:
        paths += _paths(child, (*prefix, key))
    return paths


PATHS = [_paths(encoded) for encoded, _ in VALID]


@settings(max_examples=150, deadline=None)
@given(st.data(), JSON, st.booleans())
def test_a_valid_encoding_with_one_part_replaced_decodes_or_is_refused(
    data: st.DataObject, replacement: Any, remove: bool
) -> None:
    """Damage deep inside (a field, an array's dtype or shape, a union's tag, a scan's
    channel), where arbitrary JSON from the top would rarely reach."""
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
            del parent[path[-1]]  # a field missing
        else:
            parent[path[-1]] = replacement
    _decodes_or_refuses(damaged, declared)


# ---- what a damaged file gets: one exception, and a message that says what ---------------


def _array(
    dtype: str | None = "<u2", shape: Any = (3,), raw: bytes = b"\x01\x00\x02\x00\x03\x00"
) -> Any:
    return {"dtype": dtype, "shape": list(shape), "b64": base64.b64encode(raw).decode()}


def test_a_well_formed_array_decodes() -> None:
    back = decode(_array(), np.ndarray)
    assert back.tolist() == [1, 2, 3] and back.dtype == np.uint16


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (_array(raw=b"\x01\x00\x02\x00"), "4 bytes for shape [3]"),
        (_array(shape=(2, 2)), "6 bytes for shape [2, 2]"),
        (_array(dtype="<O"), "dtype '<O'"),
        (_array(dtype="|V8", raw=b"\x00" * 24), "dtype '|V8'"),
        (_array(dtype=">u2"), "dtype '>u2'"),
        (_array(dtype=None), "dtype None"),
        (_array(shape=(-1,)), "non-negative integers"),
        (_array(shape=(True, 3)), "non-negative integers"),
        ({"dtype": "<u2", "shape": 3, "b64": ""}, "non-negative integers"),
        ({**_array(), "b64": 12}, "base64 text"),
        ({**_array(), "b64": "AQACAAMA!!"}, "not base64"),
        ([1, 2, 3], "expected an object"),
    ],
)
def test_a_damaged_array_is_a_codec_error_that_says_what(data: Any, message: str) -> None:
    with pytest.raises(CodecError, match=message.replace("[", r"\[").replace("]", r"\]")):
        decode(data, np.ndarray)


def test_a_huge_shape_is_refused_before_anything_is_allocated() -> None:
    huge = _array(dtype="<f8", shape=(2**31, 2**31, 2**31), raw=b"")
    tracemalloc.start()
    try:
        with pytest.raises(CodecError, match="larger than a recording holds"):
            decode(huge, np.ndarray)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000
    with pytest.raises(CodecError, match="larger than"):
        decode(_array(dtype="<u1", shape=(17 * 1024 * 1024,), raw=b""), np.ndarray)


def test_an_unknown_field_is_named() -> None:
    encoded = encode(GnssNoFix(1.0, "no fix"), GnssNoFix)
    with pytest.raises(CodecError, match="GnssNoFix has no field 'satellites'"):
        decode({**encoded, "satellites": 4}, GnssNoFix)
    inputs = encode(_inputs(None), ControlInputs)
    inputs["scans"]["left"]["scan"]["colour"] = "red"
    with pytest.raises(CodecError, match="Scan has no field 'colour'"):
        decode(inputs, ControlInputs)


def test_a_missing_required_field_is_named() -> None:
    encoded = encode(GnssNoFix(1.0, "no fix"), GnssNoFix)
    del encoded["reason"]
    with pytest.raises(CodecError, match=r"GnssNoFix.*reason"):
        decode(encoded, GnssNoFix)
    inputs = encode(_inputs(None), ControlInputs)
    del inputs["scans"]["right"]["sensor"]
    with pytest.raises(CodecError, match=r"MountedScan.*sensor"):
        decode(inputs, ControlInputs)


def test_a_field_of_the_wrong_type_or_an_unknown_union_arm_is_a_codec_error() -> None:
    encoded = encode(_inputs(GNSS_POSE), ControlInputs)
    for damage, message in (
        ({"gnss": {**encoded["gnss"], "_type": "GnssGuess"}}, "_type 'GnssGuess'"),
        ({"panel_seq": 1.5}, "expected an integer"),
        ({"ages_s": {"pose": "soon"}}, "expected a number"),
        ({"pc104_link": [1, 2]}, "expected an object"),
    ):
        with pytest.raises(CodecError, match=message):
            decode({**encoded, **damage}, ControlInputs)
    with pytest.raises(CodecError, match="expected 2 items, got 3"):
        decode([1, 2, 3], tuple[int, int])
    with pytest.raises(CodecError, match="expected a number"):
        decode(True, float)  # a boolean is not a number here, though Python says it is


@pytest.mark.parametrize(
    "array",
    [
        np.zeros(3, dtype=np.uint64),
        np.zeros(3, dtype=np.float16),
        np.zeros(3, dtype=np.complex128),
        np.array([object(), object()], dtype=object),
    ],
)
def test_an_array_replay_could_not_read_is_refused_when_written(array: np.ndarray) -> None:
    with pytest.raises(CodecError, match="dtype"):
        encode(array, np.ndarray)
