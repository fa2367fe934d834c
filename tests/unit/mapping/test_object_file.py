"""Object files (the worker's map as pallet poses): round trips to the float, every
problem listed with its JSON path, and "a map, or ObjectFileError, nothing else"."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.mapping.object_file import (
    DEFAULT_SIGMA_XY_M,
    DEFAULT_SIGMA_YAW_DEG,
    ObjectFileError,
    dump_object_map,
    parse_object_map,
)
from appliance.mapping.pallets import Pallet, PalletKind, PalletMap

P1 = {"name": "p1", "kind": "1100x1100", "x_m": 1.0, "y_m": 2.0, "yaw_deg": 90.0}
P2 = {"name": "p2", "kind": "1200x800", "x_m": -3.5, "y_m": 0.25, "yaw_deg": -30.5}


def file_of(*objects: dict[str, Any], **top: Any) -> bytes:
    return json.dumps({"frame": "worker", "objects": list(objects), **top}).encode()


def problems(data: bytes) -> tuple[str, ...]:
    with pytest.raises(ObjectFileError) as info:
        parse_object_map(data)
    assert str(info.value).startswith(f"{len(info.value.problems)} problem(s)")
    return info.value.problems


def assert_same_map(a: PalletMap, b: PalletMap) -> None:
    assert a.frame == b.frame
    assert len(a) == len(b)
    for p, q in zip(a.pallets, b.pallets, strict=True):
        assert (p.name, p.kind, p.x_m, p.y_m) == (q.name, q.kind, q.x_m, q.y_m)
        assert p.yaw_rad == q.yaw_rad
        assert math.copysign(1.0, p.yaw_rad) == math.copysign(1.0, q.yaw_rad)
        assert np.array_equal(p.covariance, q.covariance)


# Reading and round trips.


def test_a_file_becomes_a_pallet_map() -> None:
    sigmas = {"sigma_xy_m": 0.05, "sigma_yaw_deg": 2.0}
    pallet_map = parse_object_map(file_of(P1, {**P2, **sigmas}), source="scan.json")
    assert (pallet_map.frame, pallet_map.source, len(pallet_map)) == ("worker", "scan.json", 2)
    p1, p2 = pallet_map.pallets
    assert (p1.name, p1.kind, p1.x_m, p1.y_m, p1.support) == ("p1", PalletKind.JIS, 1.0, 2.0, 0)
    assert p1.yaw_rad == math.pi / 2
    assert p2.kind is PalletKind.EUR
    assert p2.yaw_rad == pytest.approx(math.radians(-30.5), abs=1e-15)
    default_yaw = math.radians(DEFAULT_SIGMA_YAW_DEG)
    assert np.allclose(
        p1.covariance, np.diag([DEFAULT_SIGMA_XY_M**2, DEFAULT_SIGMA_XY_M**2, default_yaw**2])
    )
    assert np.allclose(p2.covariance, np.diag([0.05**2, 0.05**2, math.radians(2.0) ** 2]))
    assert p1.covariance[0, 0] == DEFAULT_SIGMA_XY_M**2  # the sigma squared, not rounded


def test_integers_a_bom_a_default_frame_and_no_objects_are_fine() -> None:
    entry = b'{"name": "a", "kind": "1200x800", "x_m": 1, "y_m": -2, "yaw_deg": 0}'
    data = b'\xef\xbb\xbf{"objects": [' + entry + b"]}"
    pallet_map = parse_object_map(data)
    assert pallet_map.frame == "worker"
    assert (pallet_map.pallets[0].x_m, pallet_map.pallets[0].yaw_rad) == (1.0, 0.0)
    assert len(parse_object_map(b'{"frame": "site", "objects": []}')) == 0


def test_file_to_map_to_file_is_stable() -> None:
    data = file_of(P1, {**P2, "sigma_xy_m": 0.1, "sigma_yaw_deg": 0.3}, frame="terminal 7")
    first = parse_object_map(data)
    written = dump_object_map(first)
    assert_same_map(parse_object_map(written), first)
    assert dump_object_map(parse_object_map(written)) == written
    assert json.loads(written)["objects"][0] == {
        **P1,
        "sigma_xy_m": DEFAULT_SIGMA_XY_M,
        "sigma_yaw_deg": DEFAULT_SIGMA_YAW_DEG,
    }  # the short decimals a person wrote stay short


def test_the_file_is_ascii_whatever_the_names() -> None:
    pallet_map = parse_object_map(file_of({**P1, "name": 'パレット "1"'}, frame="倉庫"))
    written = dump_object_map(pallet_map)
    assert written.isascii()
    assert_same_map(parse_object_map(written), pallet_map)
    assert (
        dump_object_map(PalletMap((), "worker")) == b'{\n  "frame": "worker",\n  "objects": []\n}\n'
    )


def pallet(yaw_rad: float, sigma_xy_m: float, sigma_yaw_rad: float, name: str = "p") -> Pallet:
    covariance = np.diag([sigma_xy_m**2, sigma_xy_m**2, sigma_yaw_rad**2])
    return Pallet(1.25, -7.0, yaw_rad, covariance, PalletKind.EUR, name)


@pytest.mark.parametrize(
    "yaw_rad",
    [0.0, -0.0, math.pi, -math.pi / 2, 1e-300, 5e-324, 2 * math.pi, 0.1, 1.0000000000000002],
)
def test_any_yaw_round_trips_exactly(yaw_rad: float) -> None:
    pallet_map = PalletMap((pallet(yaw_rad, 0.03, 0.02),), "worker")
    assert_same_map(parse_object_map(dump_object_map(pallet_map)), pallet_map)


@settings(max_examples=300)
@given(
    st.lists(
        st.tuples(
            st.floats(-2 * math.pi, 2 * math.pi),
            st.floats(1e-6, 10.0),
            st.floats(math.radians(1e-6), math.pi),
            st.floats(-1e4, 1e4),
            st.sampled_from(PalletKind),
        ),
        max_size=6,
    )
)
def test_any_map_the_file_can_hold_round_trips_exactly(
    poses: list[tuple[float, float, float, float, PalletKind]],
) -> None:
    pallets = []
    for index, (yaw_rad, sigma_xy_m, sigma_yaw_rad, x_m, kind) in enumerate(poses):
        covariance = np.diag([sigma_xy_m**2, sigma_xy_m**2, sigma_yaw_rad**2])
        pallets.append(Pallet(x_m, -x_m / 3, yaw_rad, covariance, kind, f"p{index}"))
    pallet_map = PalletMap(tuple(pallets), "worker")
    written = dump_object_map(pallet_map)
    assert_same_map(parse_object_map(written), pallet_map)
    assert dump_object_map(parse_object_map(written)) == written


NAMES = st.text(min_size=1, max_size=12)
ENTRIES = st.fixed_dictionaries(
    {
        "kind": st.sampled_from([k.value for k in PalletKind]),
        "x_m": st.floats(-1e4, 1e4) | st.integers(-10_000, 10_000),
        "y_m": st.floats(-1e4, 1e4),
        "yaw_deg": st.floats(-360.0, 360.0) | st.integers(-360, 360),
    },
    optional={"sigma_xy_m": st.floats(1e-6, 10.0), "sigma_yaw_deg": st.floats(1e-6, 180.0)},
)


@settings(max_examples=200)
@given(st.lists(ENTRIES, max_size=5), st.lists(NAMES, min_size=5, max_size=5, unique=True))
def test_any_valid_file_reads_and_round_trips(
    entries: list[dict[str, Any]], names: list[str]
) -> None:
    objects = [{"name": name, **entry} for name, entry in zip(names, entries, strict=False)]
    pallet_map = parse_object_map(file_of(*objects))
    for obj, read in zip(objects, pallet_map.pallets, strict=True):
        assert (read.name, read.x_m, read.y_m) == (obj["name"], obj["x_m"], obj["y_m"])
        assert read.yaw_rad == pytest.approx(math.radians(obj["yaw_deg"]), rel=1e-15, abs=1e-300)
    assert_same_map(parse_object_map(dump_object_map(pallet_map)), pallet_map)


# Every problem, with its path.


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (b'{"objects": []}\xff', "not UTF-8: byte offset 15 (invalid start byte)"),
        (b'{"objects": [\n  {"name": "a",,}\n]}', "not JSON: line 2 column 16: Expecting"),
        (b"[" * 100_000, "not JSON this reader takes: maximum recursion depth"),
        (b"[" + b"1" * 5000 + b"]", "not JSON this reader takes: Exceeds the limit"),
        (b"[]", "(top level): should be a JSON object {...}"),
        (b"{}", "objects: Field required"),
        (b'{"objects": {}}', "objects: should be a JSON list [...]"),
        (b'{"objects": [3]}', "objects[0]: should be a JSON object {...} (got 3)"),
        (file_of(frame=""), "frame: String should have at least 1 character (got '')"),
        (file_of(colour="red"), "colour: unknown field (known: frame, objects)"),
    ],
)
def test_a_broken_file_says_where(data: bytes, expected: str) -> None:
    assert any(expected in problem for problem in problems(data)), problems(data)


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"yaw": 3.0}, "objects[1].yaw: unknown field (did you mean 'yaw_deg'? known: name, kind"),
        ({"kind": "1000x1200"}, "objects[1].kind: Input should be '1200x800' or '1100x1100'"),
        ({"x_m": "1.0"}, "objects[1].x_m: Input should be a valid number (got '1.0')"),
        ({"y_m": True}, "objects[1].y_m: Input should be a valid number (got True)"),
        ({"x_m": 1e5}, "objects[1].x_m: Input should be less than or equal to 10000"),
        ({"yaw_deg": 400.0}, "objects[1].yaw_deg: Input should be less than or equal to 360"),
        ({"yaw_deg": float("nan")}, "objects[1].yaw_deg: Input should be a finite number"),
        ({"y_m": float("-inf")}, "objects[1].y_m: Input should be a finite number"),
        ({"sigma_xy_m": 0.0}, "objects[1].sigma_xy_m: Input should be greater than or equal to"),
        ({"sigma_yaw_deg": -1.0}, "objects[1].sigma_yaw_deg: Input should be greater than or"),
        ({"name": ""}, "objects[1].name: String should have at least 1 character"),
        ({"name": 7}, "objects[1].name: Input should be a valid string (got 7)"),
        ({"name": "p1"}, "objects[1].name: 'p1' is already the name of objects[0]"),
    ],
)
def test_a_bad_object_says_which_field(change: dict[str, Any], expected: str) -> None:
    found = problems(file_of(P1, {**P2, **change}))
    assert any(expected in problem for problem in found), found


def test_a_missing_field_and_a_repeated_key() -> None:
    assert problems(file_of(P1, {k: v for k, v in P2.items() if k != "y_m"})) == (
        "objects[1].y_m: Field required",
    )
    entry = b'{"name": "a", "kind": "1200x800", "x_m": 1, "x_m": 2, "y_m": 0, "yaw_deg": 0}'
    data = b'{"objects": [' + entry + b"]}"
    assert problems(data) == (
        "objects[0].x_m: given more than once (the last one would silently win)",
    )


def test_every_problem_is_listed_at_once() -> None:
    found = problems(
        file_of(
            P1,
            {**P2, "yaw_deg": 720, "x_m": None},
            {**P1, "kind": "huge"},
            frame=3,
        )
    )
    assert found == (
        "objects[2].name: 'p1' is already the name of objects[0]",
        "frame: Input should be a valid string (got 3)",
        "objects[1].x_m: Input should be a valid number (got None)",
        "objects[1].yaw_deg: Input should be less than or equal to 360 (got 720)",
        "objects[2].kind: Input should be '1200x800' or '1100x1100' (got 'huge')",
    )


def test_a_thousand_problems_print_the_first_fifty() -> None:
    objects = [{**P1, "name": f"p{i}", "kind": "?"} for i in range(1000)]
    with pytest.raises(ObjectFileError) as info:
        parse_object_map(file_of(*objects))
    assert len(info.value.problems) == 1000
    assert str(info.value).endswith("  ... and 950 more")


def test_dump_refuses_what_the_file_cannot_hold() -> None:
    skewed = Pallet(0.0, 0.0, 0.0, np.array([[1.0, 0.1, 0], [0.1, 1.0, 0], [0, 0, 1.0]]), name="s")
    oval = Pallet(0.0, 0.0, 0.0, np.diag([1.0, 2.0, 1.0]), name="o")
    turned = pallet(7.0, 0.03, 0.01, name="t")  # 401 degrees
    with pytest.raises(ObjectFileError) as info:
        dump_object_map(PalletMap((skewed, oval, turned, pallet(0.0, 0.03, 0.01, name="")), ""))
    found = info.value.problems
    assert found[0].startswith("objects[0] ('s'): an object file holds a covariance diag(")
    assert found[1].startswith("objects[1] ('o'): an object file holds a covariance diag(")
    assert "frame: String should have at least 1 character (got '')" in found
    assert any(
        p.startswith("objects[2].yaw_deg: Input should be less than or equal to 360") for p in found
    )
    assert "objects[3].name: String should have at least 1 character (got '')" in found
    with pytest.raises(ObjectFileError, match=r"objects\[1\].name: 'a' is already the name"):
        dump_object_map(PalletMap((pallet(0, 1, 1, "a"), pallet(0, 1, 1, "a")), "worker"))


# Fuzz: a map or ObjectFileError, never anything else.

JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=20,
)


def reads_or_refuses(data: bytes) -> None:
    try:
        pallet_map = parse_object_map(data)
    except ObjectFileError:
        return
    assert all(isinstance(p, Pallet) for p in pallet_map.pallets)


@settings(max_examples=300)
@given(st.binary(max_size=200))
def test_random_bytes_read_or_raise_object_file_error(data: bytes) -> None:
    reads_or_refuses(data)


@settings(max_examples=300)
@given(
    JSON_VALUES,
    st.lists(st.fixed_dictionaries({}, optional={k: JSON_VALUES for k in P1}), max_size=3),
)
def test_random_json_reads_or_raises_object_file_error(value: Any, objects: list[Any]) -> None:
    reads_or_refuses(json.dumps(value).encode())
    reads_or_refuses(json.dumps({"frame": value, "objects": objects}).encode())
    reads_or_refuses(json.dumps({"objects": [{**P1, key: value} for key in P1]}).encode())
