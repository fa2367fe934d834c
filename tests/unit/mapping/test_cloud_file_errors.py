"""PLY point clouds: every defect is a CloudFileError that says where it is."""

from __future__ import annotations

import struct
import time
from typing import Any

import numpy as np
import pytest

from appliance.mapping.cloud_file import CloudFileError, PointCloud, parse_ply, write_ply
from tests.unit.mapping.ply_samples import (
    FORMATS,
    GOOD_ASCII,
    VERTEX_XYZ,
    XYZ,
    ascii_file,
    binary_by_hand,
    error,
    header,
)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "not a PLY file"),
        (b"PLY\nformat ascii 1.0\nend_header\n", "not a PLY file"),
        (b"plyformat ascii 1.0\n", "not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\n", "no end_header line (after line 3)"),
        (header("element vertex 0", fmt="binary_middle_endian"), "header line 2: unknown format"),
        (b"ply\nformat ascii 2.0\nend_header\n", "header line 2: unknown format"),
        (b"ply\nelement vertex 0\nend_header\n", "the header has no format line"),
        (header("format ascii 1.0"), "header line 3: a second format line"),
        (header("element vertex 1", "property float16 x"), "header line 4: unknown property type"),
        (header("property float x"), "header line 3: a property before any element"),
        (header("element vertex two"), "header line 3: an element line is"),
        (header("element vertex 1", "property x"), "header line 4: a property line is"),
        (header("element face 1", "property list float int v"), "header line 4: a list's length"),
        (header("element vertex 1", "element vertex 1"), "header line 4: a second element"),
        (header("elephant 3"), "header line 3: unknown header line 'elephant 3'"),
        (header("element face 0"), "no 'vertex' element"),
        (header("comment dbw origin 1 2"), "header line 3: a viewpoint is"),
        (header("comment dbw origin 1 2 nan"), "header line 3: viewpoint (1.0, 2.0, nan)"),
    ],
)
def test_a_bad_header_says_which_line(data: bytes, message: str) -> None:
    assert message in error(data)


def test_duplicate_property() -> None:
    data = header("element vertex 1", "property float x", "property float y", "property int x")
    assert "header line 6: duplicate property 'x' in element 'vertex'" in error(data)


@pytest.mark.parametrize(
    ("properties", "missing"),
    [(["property float x", "property float y"], "z"), (["property list uchar float x"], "x, y, z")],
)
def test_a_vertex_element_needs_scalar_x_y_z(properties: list[str], missing: str) -> None:
    assert f"no scalar property {missing}" in error(header("element vertex 0", *properties))


def test_a_negative_count() -> None:
    assert "header line 3: element 'face' has a negative count -1" in error(
        header("element face -1", *VERTEX_XYZ)
    )


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_an_absurd_vertex_count_is_refused_before_allocating(fmt: str) -> None:
    data = header(*("element vertex 1000000000000", *VERTEX_XYZ[1:]), fmt=fmt) + b"1 2 3\n"
    started = time.perf_counter()
    assert "header line 3: 1000000000000 vertices is more than max_points=50000000" in error(data)
    # With the limit raised, the bytes at hand still bound what is read.
    expected = {
        "ascii": "the file ends after line 8, before element 'vertex' index 1 of 1000000000000",
        "binary_little_endian": f"truncated at byte offset {len(data) - 6} of {len(data)}: "
        "element 'vertex' index 0 of 1000000000000",
    }
    assert expected[fmt] in error(data, max_points=10**13)
    assert time.perf_counter() - started < 1.0  # allocating first would take far longer
    assert "3 vertices is more than max_points=2" in error(
        header("element vertex 3", *VERTEX_XYZ[1:]), max_points=2
    )


def test_a_truncated_binary_body_says_where() -> None:
    data = write_ply(XYZ)  # 12 bytes a point
    start = len(data) - 36
    assert (
        f"truncated at byte offset {start + 24} of {len(data) - 5}: element 'vertex' index 2"
        in error(data[:-5])
    )
    faces, _ = binary_by_hand("<")
    message = error(faces[:-17])  # the edges (16 bytes) and the last face's short
    assert "element 'face' index 2 of 3 is incomplete" in message


def test_a_negative_list_length_in_binary() -> None:
    data = header(*VERTEX_XYZ, "element face 1", "property list char int v")
    data += struct.pack("<6fb", 0, 0, 0, 1, 1, 1, -1)
    assert "element 'face' index 0): list 'v' has length -1" in error(data)


def test_garbage_after_a_binary_body_is_refused() -> None:
    data = write_ply(XYZ)
    assert f"3 bytes of extra data after the body (from byte offset {len(data)})" in error(
        data + b"\n\n\n"
    )


def test_trailing_whitespace_after_an_ascii_body_is_fine() -> None:
    assert len(parse_ply(GOOD_ASCII + b"\n \r\n\t\n")) == 2


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (["1 2 3", "4 5 6", "7 8 9"], "line 10: data after the last element"),
        (["1 2 3", "4 5"], "line 9 (element 'vertex' index 1): too few values (no 'z')"),
        (
            ["1 2 3 4", "4 5 6"],
            "line 8 (element 'vertex' index 0): too many values (4, expected 3)",
        ),
        (["1 2 3", "4 abc 6"], "line 9 (element 'vertex' index 1): 'abc' is not a number ('y')"),
        (["1 2 3"], "the file ends after line 8, before element 'vertex' index 1 of 2"),
    ],
)
def test_a_bad_ascii_body_says_which_line(body: list[str], message: str) -> None:
    assert message in error(ascii_file(*VERTEX_XYZ, "---", *body))


def test_bad_ascii_lists_and_integers() -> None:
    face = ("element face 1", "property list uchar int v")
    base = (*VERTEX_XYZ, *face, "---", "1 2 3", "4 5 6")
    assert "line 12 (element 'face' index 0): too few values for list 'v'" in error(
        ascii_file(*base, "3 0 1")
    )
    assert "list 'v' has length -1" in error(ascii_file(*base, "-1"))
    assert "list 'v' needs a length" in error(ascii_file(*base, "x 1"))
    assert "line 12 (element 'face' index 0): '1.5' is not an integer ('v')" in error(
        ascii_file(*base, "1 1.5")
    )
    ints = ("element vertex 1", "property int x", "property int y", "property int z")
    assert "line 8 (element 'vertex' index 0): 'nan' is not an integer ('y')" in error(
        ascii_file(*ints, "---", "1 nan 3")
    )
    not_ascii = GOOD_ASCII.replace(b"4 5", b"4 \xe9")
    offset = not_ascii.index(b"\xe9")
    assert f"line 9: a byte that is not ASCII (offset {offset})" in error(not_ascii)


@pytest.mark.parametrize("form", FORMATS)
def test_non_finite_points_are_refused_or_dropped(form: dict[str, Any]) -> None:
    xyz = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [np.nan, 0.0, 0.0], [0.0, -np.inf, 1.0]])
    data = write_ply(XYZ, **form)
    # write_ply refuses NaN, so put them in by hand: a scanner's "no return".
    if form["binary"]:
        endian = ">" if form.get("big_endian") else "<"
        data = data[:-36] + xyz.astype(endian + "f4").tobytes()
        data = data.replace(b"vertex 3", b"vertex 4")
    else:
        data = data.split(b"end_header\n")[0].replace(b"vertex 3", b"vertex 4") + (
            b"end_header\n1 2 3\n4 5 6\nnan 0 0\n0 -inf 1\n"
        )
    assert "vertex 2 has a non-finite coordinate (nan, 0.0, 0.0)" in error(data)
    cloud = parse_ply(data, drop_non_finite=True)
    assert cloud.xyz_m.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    assert cloud.dropped_non_finite == 2


def test_write_ply_refuses_what_it_cannot_write() -> None:
    with pytest.raises(CloudFileError, match=r"point 1 \(inf, 0.0, 0.0\) is not finite as float32"):
        write_ply([[0.0, 0.0, 0.0], [1e39, 0.0, 0.0]])
    assert parse_ply(write_ply([[1e39, 0.0, 0.0]], double=True)).xyz_m[0, 0] == 1e39
    with pytest.raises(CloudFileError, match="is not finite"):
        write_ply([[np.nan, 0.0, 0.0]], double=True)
    with pytest.raises(CloudFileError, match=r"an \(N, 3\) array, not \(2, 2\)"):
        write_ply([[0.0, 0.0], [1.0, 1.0]])
    with pytest.raises(CloudFileError, match="one line"):
        write_ply(XYZ, comments=["two\nlines"])
    with pytest.raises(CloudFileError, match="would read back as a viewpoint"):
        write_ply(XYZ, comments=["dbw origin 1 2 3"])
    with pytest.raises(CloudFileError, match="viewpoint"):
        write_ply(XYZ, origins_m=[(1.0, 2.0)])
    with pytest.raises(CloudFileError, match="not finite"):
        write_ply(XYZ, origins_m=[(1.0, 2.0, float("inf"))])


def test_a_point_cloud_is_n_by_3() -> None:
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        PointCloud(np.zeros((4, 2)))
