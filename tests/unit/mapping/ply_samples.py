"""PLY files for the cloud-file tests, written by hand (never by write_ply) so that the
reader is checked against an independent writer."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from appliance.mapping.cloud_file import CloudFileError, parse_ply

FORMATS = [
    pytest.param({"binary": True}, id="binary_little_endian"),
    pytest.param({"binary": True, "big_endian": True}, id="binary_big_endian"),
    pytest.param({"binary": False}, id="ascii"),
]
XYZ = np.array([[0.0, 1.5, -2.25], [1e-3, 123.456, 7.0], [-50.0, 0.1, 3.0]])


def header(*lines: str, fmt: str = "binary_little_endian") -> bytes:
    return ("\n".join(["ply", f"format {fmt} 1.0", *lines, "end_header"]) + "\n").encode()


def ascii_file(*lines: str) -> bytes:
    """A hand-written ascii file: header lines, then "---", then body lines."""
    cut = lines.index("---")
    return header(*lines[:cut], fmt="ascii") + "".join(f"{x}\n" for x in lines[cut + 1 :]).encode()


VERTEX_XYZ = ("element vertex 2", "property float x", "property float y", "property float z")
GOOD_ASCII = ascii_file(*VERTEX_XYZ, "---", "1 2 3", "4 5 6")


def error(data: bytes, **kwargs: object) -> str:
    with pytest.raises(CloudFileError) as info:
        parse_ply(data, **kwargs)  # type: ignore[arg-type]
    return str(info.value)


def binary_by_hand(endian: str) -> tuple[bytes, list[tuple[float, float, float]]]:
    """Vertices with normals, colour and intensity between a camera element and faces
    and edges, packed with struct: a writer independent of write_ply."""
    points = [(1.5, -2.0, 0.25), (10.0, 20.0, 30.0), (-0.5, 0.0, 7.75)]
    fmt = "binary_big_endian" if endian == ">" else "binary_little_endian"
    head = header(
        "element camera 1", "property double view_x", "property uint8 flags",
        "element vertex 3", "property double nx", "property float x", "property float y",
        "property uchar red", "property double z", "property ushort intensity",
        "element face 3", "property list uchar int vertex_indices", "property short material",
        "element edge 2", "property int vertex1", "property int vertex2",
        fmt=fmt,
    )  # fmt: skip
    body = struct.pack(endian + "dB", 1.25, 7)
    for index, (x, y, z) in enumerate(points):
        body += struct.pack(endian + "dffBdH", 0.5, x, y, 200 + index, z, 65535)
    for indices in ([0, 1, 2], [], [2, 1, 0, 1]):
        body += struct.pack(endian + f"B{len(indices)}ih", len(indices), *indices, -3)
    body += struct.pack(endian + "4i", 0, 1, 1, 2)
    return head + body, points
