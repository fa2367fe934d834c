"""PLY point clouds: round trips, files written by hand (not by write_ply), and the fuzz
property "a cloud, or CloudFileError, nothing else" (each error: test_cloud_file_errors)."""

from __future__ import annotations

import struct
import time
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from appliance.mapping.cloud_file import CloudFileError, parse_ply, write_ply
from tests.unit.mapping.ply_samples import (
    FORMATS,
    GOOD_ASCII,
    XYZ,
    ascii_file,
    binary_by_hand,
    header,
)

# Round trips.


@pytest.mark.parametrize("form", FORMATS)
@pytest.mark.parametrize("double", [False, True])
def test_round_trip_in_every_format(form: dict[str, Any], double: bool) -> None:
    data = write_ply(
        XYZ, double=double, comments=["scan 1", "  spaced "], obj_info=["ipad"],
        origins_m=[(0.0, 0.0, 1.2), (3.5, -1.0, 1.25)], **form,
    )  # fmt: skip
    cloud = parse_ply(data)
    expected = XYZ if double else XYZ.astype(np.float32).astype(np.float64)
    assert np.array_equal(cloud.xyz_m, expected)
    assert cloud.comments == ("scan 1", "  spaced ")
    assert cloud.obj_info == ("ipad",)
    assert cloud.origins_m == ((0.0, 0.0, 1.2), (3.5, -1.0, 1.25))
    assert cloud.dropped_non_finite == 0
    assert len(cloud) == 3


@pytest.mark.parametrize("form", FORMATS)
def test_an_empty_cloud_is_a_cloud(form: dict[str, Any]) -> None:
    cloud = parse_ply(write_ply(np.empty((0, 3)), **form))
    assert cloud.xyz_m.shape == (0, 3)
    assert parse_ply(write_ply([], **form)).xyz_m.shape == (0, 3)


def test_the_points_are_read_only() -> None:
    cloud = parse_ply(write_ply(XYZ))
    with pytest.raises(ValueError, match="read-only"):
        cloud.xyz_m[0, 0] = 1.0


@settings(max_examples=150)
@given(
    xyz=hnp.arrays(
        np.float64,
        st.tuples(st.integers(0, 30), st.just(3)),
        elements=st.floats(-1e30, 1e30, allow_nan=False, allow_infinity=False),
    ),
    form=st.sampled_from([(True, False), (True, True), (False, False)]),
    double=st.booleans(),
    comments=st.lists(st.text().filter(lambda t: "\n" not in t and "\r" not in t), max_size=3),
)
def test_any_cloud_round_trips(
    xyz: np.ndarray, form: tuple[bool, bool], double: bool, comments: list[str]
) -> None:
    comments = [c for c in comments if c.split()[:2] != ["dbw", "origin"]]
    binary, big_endian = form
    cloud = parse_ply(
        write_ply(xyz, binary=binary, big_endian=big_endian, double=double, comments=comments)
    )
    expected = xyz if double else xyz.astype(np.float32).astype(np.float64)
    assert np.array_equal(cloud.xyz_m, expected)
    assert cloud.comments == tuple(comments)


# Files written by hand: extra properties, other elements, lists, both byte orders.


def test_hand_written_ascii_with_extra_properties_and_elements() -> None:
    data = ascii_file(
        "comment made by hand",
        "element camera 1",
        "property float view_x",
        "property list uchar float k",
        "element vertex 3",
        "property double nx",
        "property float x",
        "property uchar red",
        "property float y",
        "property float z",
        "property int16 intensity",
        "element face 2",
        "property list uchar int vertex_indices",
        "element edge 1",
        "property int vertex1",
        "property int vertex2",
        "---",
        "0.5 3 1 2 3",
        "0.1 1.0 255 2.0 3.0 -7",
        "",
        "  0.2 4 0 5 6e0 12  ",
        "0.3 -7.5 9 8.25 1e2 0",
        "3 0 1 2",
        "0",
        "0 2",
        "   ",
    )
    cloud = parse_ply(data)
    assert cloud.xyz_m.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [-7.5, 8.25, 100.0]]
    assert cloud.comments == ("made by hand",)
    assert cloud.origins_m == ()


@pytest.mark.parametrize("endian", ["<", ">"])
def test_hand_packed_binary_with_extra_properties_and_a_face_list(endian: str) -> None:
    data, points = binary_by_hand(endian)
    assert parse_ply(data).xyz_m.tolist() == [list(p) for p in points]


@pytest.mark.parametrize("endian", ["<", ">"])
def test_a_vertex_element_with_a_list_property(endian: str) -> None:
    fmt = "binary_big_endian" if endian == ">" else "binary_little_endian"
    head = header(
        "element vertex 2", "property list uchar float tags", "property int8 x",
        "property int32 y", "property float64 z", fmt=fmt,
    )  # fmt: skip
    body = struct.pack(endian + "B2fbid", 2, 1.0, 2.0, -3, 40000, 0.5)
    body += struct.pack(endian + "Bbid", 0, 4, -5, 6.5)
    assert parse_ply(head + body).xyz_m.tolist() == [[-3.0, 40000.0, 0.5], [4.0, -5.0, 6.5]]
    data = ascii_file(
        *head.decode().split("\n")[2:-2], "---", "2 1.0 2.0 -3 40000 0.5", "0 4 -5 6.5"
    )
    assert parse_ply(data).xyz_m.tolist() == [[-3.0, 40000.0, 0.5], [4.0, -5.0, 6.5]]


def test_windows_line_endings_in_the_header_and_an_ascii_body() -> None:
    data = GOOD_ASCII.replace(b"\n", b"\r\n")
    assert parse_ply(data).xyz_m.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    binary = write_ply(XYZ).replace(b"\n", b"\r\n", 7)  # the header's seven lines only
    assert np.array_equal(parse_ply(binary).xyz_m, XYZ.astype(np.float32))


def test_a_million_binary_points_parse_in_well_under_a_second() -> None:
    data = write_ply(np.random.default_rng(1).normal(size=(1_000_000, 3)))
    started = time.perf_counter()
    assert len(parse_ply(data)) == 1_000_000
    assert time.perf_counter() - started < 0.5


# Fuzz: a cloud or CloudFileError, never anything else.

VALID = [
    write_ply(XYZ, origins_m=[(1.0, 2.0, 3.0)]),
    write_ply(XYZ, binary=False),
    write_ply(XYZ, big_endian=True, double=True),
    binary_by_hand("<")[0],
    binary_by_hand(">")[0],
    GOOD_ASCII,
]


def parses_or_refuses(data: bytes) -> None:
    try:
        cloud = parse_ply(data)
    except CloudFileError:
        return
    assert cloud.xyz_m.shape[1] == 3


@settings(max_examples=300)
@given(which=st.sampled_from(VALID[:1] + VALID[2:5]), data=st.data())
def test_any_truncation_of_a_binary_file_raises_cloud_file_error(
    which: bytes, data: st.DataObject
) -> None:
    cut = data.draw(st.integers(0, len(which) - 1))
    with pytest.raises(CloudFileError):
        parse_ply(which[:cut])


@settings(max_examples=300)
@given(st.binary(max_size=300))
def test_random_bytes_parse_or_raise_cloud_file_error(data: bytes) -> None:
    parses_or_refuses(data)
    parses_or_refuses(b"ply\n" + data)
    parses_or_refuses(b"ply\nformat binary_little_endian 1.0\n" + data)


@settings(max_examples=500)
@given(which=st.sampled_from(VALID), data=st.data())
def test_mutated_files_parse_or_raise_cloud_file_error(which: bytes, data: st.DataObject) -> None:
    mutated = bytearray(which)
    for _ in range(data.draw(st.integers(1, 4))):
        position = data.draw(st.integers(0, len(mutated) - 1))
        mutated[position] = data.draw(
            st.sampled_from(b"0123456789-+. \n\r\x00\xffxyzlist" + bytes(range(256)))
        )
    parses_or_refuses(bytes(mutated))


@settings(max_examples=300)
@given(
    which=st.sampled_from(VALID),
    line=st.integers(1, 20),
    replacement=st.sampled_from(
        [
            "element vertex -1",
            "element vertex 99",
            "element face 5",
            "property list uchar int x",
            "property list int double q",
            "property uint x",
            "property char w",
            "format ascii 1.0",
            "format binary_big_endian 1.0",
            "comment dbw origin 1 2",
            "end_header",
            "",
            "element",
        ]
    ),
)
def test_mutated_header_lines_parse_or_raise_cloud_file_error(
    which: bytes, line: int, replacement: str
) -> None:
    lines = which.split(b"\n")
    if line < len(lines) - 1 and b"end_header" not in b"\n".join(lines[:line]):
        lines[line] = replacement.encode()
    parses_or_refuses(b"\n".join(lines))
