"""The compiled decoders make the very objects the reference decoder makes: the same types,
equal, with the same attributes in the same order, whether a record is made by calling
its class or stored field by field; an enum member is the one its class returns; and an
array is the reference's array, or refused by both."""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import InitVar, dataclass
from typing import Any, NamedTuple

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from appliance.core.inputs import ControlInputs
from appliance.recording.codec import CodecError, decode, encode
from appliance.recording.fastdecode import _direct_constructor, decode_fast
from drivers.lms111.mounted import MountedScan
from tests.unit.recording.test_codec import ARRAY_DTYPES, GNSS_POSE, _inputs, _scans


def same_objects(a: Any, b: Any, where: str = "$") -> None:
    assert type(a) is type(b), where
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), where
        assert a.flags.writeable == b.flags.writeable, where
    elif dataclasses.is_dataclass(a):
        assert list(vars(a)) == list(vars(b)), where
        for name in vars(a):
            same_objects(getattr(a, name), getattr(b, name), f"{where}.{name}")
    elif isinstance(a, tuple | list):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            same_objects(x, y, f"{where}[{k}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for key in a:
            same_objects(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, float):
        assert a.hex() == b.hex() or (a != a and b != b), where
    else:
        assert a == b, where


@pytest.mark.parametrize("gnss", [GNSS_POSE, None])
def test_inputs_and_scans_decode_to_the_same_objects(gnss: Any) -> None:
    encoded = encode(_inputs(gnss), ControlInputs)
    fast, reference = decode_fast(encoded, ControlInputs), decode(encoded, ControlInputs)
    same_objects(fast, reference)
    for scan in _scans().values():
        if scan is not None:
            encoded = encode(scan, MountedScan)
            same_objects(decode_fast(encoded, MountedScan), decode(encoded, MountedScan))
            # what a scan computes on first use, it computes the same
            fast_scan = decode_fast(encoded, MountedScan)
            assert fast_scan.angles_vehicle_rad.tobytes() == scan.angles_vehicle_rad.tobytes()


class Colour(enum.IntEnum):
    RED = 1
    GREEN = 2


class Shade(enum.Enum):
    DARK = "dark"
    LIGHT = (1, 2)


@pytest.mark.parametrize(
    ("data", "declared"),
    [
        *[(data, Colour) for data in (1, True, 2.0, 3, "1", [1])],
        *[(data, Shade) for data in ("dark", [1, 2], {"a": 1}, None)],
    ],
)
def test_an_enum_member_is_the_one_its_class_returns(data: Any, declared: Any) -> None:
    try:
        expected: Any = decode(data, declared)
    except CodecError:
        with pytest.raises(CodecError):
            decode_fast(data, declared)
        return
    assert decode_fast(data, declared) is expected


@dataclass(frozen=True)
class Plain:
    a: int
    b: float = 0.0


@dataclass(frozen=True)
class Checked:
    a: int

    def __post_init__(self) -> None:
        if self.a < 0:
            raise ValueError("negative")


@dataclass(frozen=True)
class Derived:
    a: int
    scale: InitVar[int] = 1


@dataclass(frozen=True, slots=True)
class Slotted:
    a: int


@dataclass
class Mutable:
    a: int


@dataclass(frozen=True, init=False)
class OwnInit:
    a: int

    def __init__(self, a: int) -> None:
        object.__setattr__(self, "a", a * 2)


class Pair(NamedTuple):
    a: int
    b: int


@pytest.mark.parametrize(
    ("cls", "direct"),
    [
        (Plain, True),
        (Checked, False),
        (Derived, False),
        (Slotted, False),
        (Mutable, False),
        (OwnInit, False),
        (Pair, False),
    ],
)
def test_only_a_class_whose_init_just_stores_its_fields_skips_it(cls: type, direct: bool) -> None:
    names = [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls) else ["a"]
    assert (_direct_constructor(cls, names) is not None) is direct


def test_a_class_with_a_post_init_still_runs_it() -> None:
    assert decode_fast({"a": 3}, Checked) == Checked(3)
    with pytest.raises(CodecError):
        decode_fast({"a": -1}, Checked)
    assert decode_fast({"a": 2}, OwnInit).a == 4
    plain = decode_fast({"a": 1, "b": 2.5}, Plain)
    assert plain == Plain(1, 2.5) and list(vars(plain)) == ["a", "b"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        plain.a = 2  # type: ignore[misc]
    assert decode_fast({"a": 1}, Plain) == Plain(1)  # a default: made by calling the class


def _array_outcome(decoder: Any, data: Any) -> Any:
    try:
        return decoder(data, np.ndarray)
    except CodecError:
        return CodecError


@settings(max_examples=150, deadline=None)
@given(
    hnp.arrays(ARRAY_DTYPES, hnp.array_shapes(min_dims=0, max_dims=2, min_side=0, max_side=6)),
    st.sampled_from(["<", ">"]),
    st.sampled_from(["none", "b64", "shape", "dtype", "extra", "missing"]),
    st.data(),
)
def test_an_array_decodes_as_the_reference_decodes_it(
    array: np.ndarray, order: str, damage: str, data: st.DataObject
) -> None:
    """Whole, or with one part replaced: the same array (dtype, shape, bytes, read-only),
    or a refusal from both."""
    encoded = encode(array.astype(array.dtype.newbyteorder(order)), np.ndarray)
    if damage == "b64":
        encoded["b64"] = data.draw(st.text(alphabet="AB=+/!é \n", max_size=12) | st.integers())
    elif damage == "shape":
        encoded["shape"] = data.draw(st.lists(st.integers(-2, 8) | st.booleans(), max_size=2))
    elif damage == "dtype":
        encoded["dtype"] = data.draw(st.sampled_from(["<u2", "|u1", ">u2", "<f2", 5, None]))
    elif damage == "extra":
        encoded["note"] = 1
    elif damage == "missing":
        del encoded[data.draw(st.sampled_from(["dtype", "shape", "b64"]))]
    fast, reference = _array_outcome(decode_fast, encoded), _array_outcome(decode, encoded)
    if reference is CodecError or fast is CodecError:
        assert fast is reference
        return
    same_objects(fast, reference)
