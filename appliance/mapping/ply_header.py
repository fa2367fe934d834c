"""The header of a PLY file: what elements follow, with which properties, in which encoding.

Split from `mapping.cloud_file` (which reads the body and writes files) because the header
is where a PLY file says everything about itself: every count, type and name is checked
here, against the header line it came from, before a byte of the body is looked at.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

# A large warehouse scanned densely is tens of millions of points; more is a corrupt count.
DEFAULT_MAX_POINTS = 50_000_000
ORIGIN_COMMENT = "dbw origin"

# PLY scalar types as struct/numpy type characters (both use the same letters for these).
_SCALARS = {"char": "b", "uchar": "B", "short": "h", "ushort": "H", "int": "i", "uint": "I"}
_SCALARS |= {"float": "f", "double": "d", "int8": "b", "uint8": "B", "int16": "h"}
_SCALARS |= {"uint16": "H", "int32": "i", "uint32": "I", "float32": "f", "float64": "d"}
_FORMATS = {"ascii": "ascii", "binary_little_endian": "<", "binary_big_endian": ">"}
INTEGER = re.compile(r"[+-]?[0-9]{1,20}")


class CloudFileError(ValueError):
    """A point-cloud file that cannot be read (or a cloud that cannot be written)."""


@dataclass(frozen=True)
class PlyProperty:
    """One property of an element, by its struct/numpy type letters."""

    name: str
    type_char: str  # the value's type; the items' type for a list
    count_char: str | None = None  # a list property's length type


@dataclass(frozen=True)
class PlyElement:
    """One element: its rows' count and layout."""

    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    @property
    def has_lists(self) -> bool:
        return any(p.count_char is not None for p in self.properties)


@dataclass(frozen=True)
class PlyHeader:
    """Everything the header says, and where the body starts."""

    encoding: str  # "ascii", "<" or ">"
    elements: tuple[PlyElement, ...]
    comments: tuple[str, ...]
    obj_info: tuple[str, ...]
    origins_m: tuple[tuple[float, float, float], ...]
    body_start: int  # byte offset of the first byte after end_header's newline
    line_count: int  # header lines, end_header included


def parse_header(data: bytes, max_points: int) -> PlyHeader:
    """The header of ``data``, every line checked, or `CloudFileError` naming the line.

    Header text is decoded leniently (invalid UTF-8 becomes U+FFFD): a consumer app's
    comment in some local code page must not cost the worker their map, and a keyword
    that is not ASCII fails as an unknown keyword anyway.
    """
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise CloudFileError("not a PLY file: it does not start with a 'ply' line")
    encoding: str | None = None
    elements: list[PlyElement] = []
    comments: list[str] = []
    obj_info: list[str] = []
    origins: list[tuple[float, float, float]] = []
    start, line_no = data.index(b"\n") + 1, 1
    while True:
        end = data.find(b"\n", start)
        if end < 0:
            raise CloudFileError(f"the header has no end_header line (after line {line_no})")
        line_no += 1
        line = data[start:end].decode("utf-8", errors="replace").removesuffix("\r").lstrip()
        start = end + 1
        tokens = line.split()
        keyword = tokens[0] if tokens else ""
        where = f"header line {line_no}"
        if keyword == "end_header" and len(tokens) == 1:
            break
        if keyword in ("comment", "obj_info"):
            text = line[len(keyword) + 1 :]
            if keyword == "obj_info":
                obj_info.append(text)
            elif text.split()[:2] == ORIGIN_COMMENT.split():
                origins.append(parse_origin(text.split()[2:], where))
            else:
                comments.append(text)
        elif keyword == "format":
            if encoding is not None:
                raise CloudFileError(f"{where}: a second format line")
            if len(tokens) != 3 or tokens[1] not in _FORMATS or tokens[2] != "1.0":
                raise CloudFileError(
                    f"{where}: unknown format {line!r} (known: "
                    + ", ".join(f"'format {name} 1.0'" for name in _FORMATS)
                    + ")"
                )
            encoding = _FORMATS[tokens[1]]
        elif keyword == "element":
            elements.append(_parse_element(tokens, elements, max_points, where))
        elif keyword == "property":
            if not elements:
                raise CloudFileError(f"{where}: a property before any element")
            prop = _parse_property(tokens, where)
            last = elements[-1]
            if any(p.name == prop.name for p in last.properties):
                raise CloudFileError(
                    f"{where}: duplicate property {prop.name!r} in element {last.name!r}"
                )
            elements[-1] = PlyElement(last.name, last.count, (*last.properties, prop))
        elif keyword:
            raise CloudFileError(f"{where}: unknown header line {line[:60]!r}")
    if encoding is None:
        raise CloudFileError("the header has no format line")
    _check_vertex_element(elements)
    return PlyHeader(
        encoding,
        tuple(elements),
        tuple(comments),
        tuple(obj_info),
        tuple(origins),
        start,
        line_no,
    )


def parse_origin(tokens: list[str], where: str) -> tuple[float, float, float]:
    """A viewpoint's three coordinates; ours, so a malformed one is an error, not a comment."""
    try:
        x, y, z = (float(token) for token in tokens)
    except ValueError:
        raise CloudFileError(
            f"{where}: a viewpoint is 'comment {ORIGIN_COMMENT} X Y Z', got {tokens!r}"
        ) from None
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise CloudFileError(f"{where}: viewpoint {(x, y, z)} is not finite")
    return x, y, z


def _parse_element(
    tokens: list[str], elements: list[PlyElement], max_points: int, where: str
) -> PlyElement:
    if len(tokens) != 3 or not INTEGER.fullmatch(tokens[2]):
        raise CloudFileError(f"{where}: an element line is 'element NAME COUNT', got {tokens}")
    name, count = tokens[1], int(tokens[2])
    if any(element.name == name for element in elements):
        raise CloudFileError(f"{where}: a second element {name!r}")
    if count < 0:
        raise CloudFileError(f"{where}: element {name!r} has a negative count {count}")
    if name == "vertex" and count > max_points:
        raise CloudFileError(
            f"{where}: {count} vertices is more than max_points={max_points}: "
            "a corrupt count, or raise max_points"
        )
    return PlyElement(name, count, ())


def _parse_property(tokens: list[str], where: str) -> PlyProperty:
    if len(tokens) == 3:
        return PlyProperty(tokens[2], _scalar_char(tokens[1], where))
    if len(tokens) == 5 and tokens[1] == "list":
        count_char = _scalar_char(tokens[2], where)
        if count_char in "fd":
            raise CloudFileError(f"{where}: a list's length type must be an integer type")
        return PlyProperty(tokens[4], _scalar_char(tokens[3], where), count_char)
    raise CloudFileError(
        f"{where}: a property line is 'property TYPE NAME' or "
        f"'property list COUNT_TYPE ITEM_TYPE NAME', got {tokens}"
    )


def _scalar_char(type_name: str, where: str) -> str:
    if type_name not in _SCALARS:
        raise CloudFileError(f"{where}: unknown property type {type_name!r}")
    return _SCALARS[type_name]


def _check_vertex_element(elements: list[PlyElement]) -> None:
    vertex = next((element for element in elements if element.name == "vertex"), None)
    if vertex is None:
        raise CloudFileError("the header declares no 'vertex' element")
    scalars = {p.name for p in vertex.properties if p.count_char is None}
    missing = [axis for axis in "xyz" if axis not in scalars]
    if missing:
        raise CloudFileError(f"the vertex element has no scalar property {', '.join(missing)}")
