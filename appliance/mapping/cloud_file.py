"""The worker's map as a file: an XYZ point cloud in PLY, read and written without I/O.

Kinouchi et al. (section 2.1) have the worker scan the storage area with a handheld 3D
LiDAR; what reaches the vehicle is that terminal's point cloud, and PLY is what consumer
scanners and their apps (and CloudCompare, Open3D, MeshLab) export. The format is Greg
Turk's (the description tools follow is on Paul Bourke's pages): a text header (``ply``,
``format``, ``comment``, ``obj_info``, ``element``, ``property``, ``end_header``) then
the elements in order, as ascii lines or packed little/big-endian binary. We keep the
vertices' x, y, z and read past everything else (normals, colours, faces, lists),
because a file that carries more than we need is still a good map.

Lenient only where nothing can be misread: CRLF line ends, blank lines and trailing
whitespace in an ascii body, header text that is not UTF-8 (replaced). An ascii value is
taken as written (a ``float`` column is not rounded to float32), but an integer column
must hold whole numbers, and a binary body must end exactly where its last element does.

The file comes from a device we do not control, so every defect is a `CloudFileError`
naming the header line, or the body line / byte offset and element index, and nothing
else escapes: the CLI prints it, the daemon logs it, and neither needs a second
``except``. Sizes are checked against the bytes at hand before anything is allocated.

Scan viewpoints travel as comments, ``comment dbw origin X Y Z`` (metres, the cloud's
frame), one per viewpoint: the pallet detector needs the sensor origin for its proximity
points (section 2.2) and PLY has no field for it. Our simulated worker's terminal writes
them; other tools' clouds have none, which is fine.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.mapping.ply_header import (
    DEFAULT_MAX_POINTS,
    INTEGER,
    ORIGIN_COMMENT,
    CloudFileError,
    PlyElement,
    PlyHeader,
    PlyProperty,
    parse_header,
    parse_origin,
)

__all__ = ["DEFAULT_MAX_POINTS", "CloudFileError", "PointCloud", "parse_ply", "write_ply"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class PointCloud:
    """A worker's map as read: the points and what the header said about them.

    ``origins_m`` are the scan viewpoints from ``comment dbw origin X Y Z`` lines, which
    are not repeated in ``comments``.
    """

    xyz_m: FloatArray  # (N, 3), read-only
    comments: tuple[str, ...] = ()  # without the origin comments, which are parsed below
    obj_info: tuple[str, ...] = ()
    origins_m: tuple[tuple[float, float, float], ...] = ()
    dropped_non_finite: int = 0  # points with NaN/inf left out (``drop_non_finite=True``)

    def __post_init__(self) -> None:
        xyz = np.array(self.xyz_m, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"a point cloud is an (N, 3) array, not {xyz.shape}")
        xyz.flags.writeable = False
        object.__setattr__(self, "xyz_m", xyz)

    def __len__(self) -> int:
        return int(self.xyz_m.shape[0])


def parse_ply(
    data: bytes, *, max_points: int = DEFAULT_MAX_POINTS, drop_non_finite: bool = False
) -> PointCloud:
    """The cloud in ``data`` (a whole PLY file), or `CloudFileError` saying what is wrong.

    A NaN or infinite coordinate is refused (with the vertex index) unless
    ``drop_non_finite``: some scanners mark "no return" that way, and dropping such points
    is then the right reading, but only if the caller says so. Binary files go through
    numpy in one pass (about 30 ms for a million points); ascii is parsed line by line,
    about 2.5 s for a million.
    """
    header = parse_header(data, max_points)
    if header.encoding == "ascii":
        xyz = _read_ascii_body(data, header)
    else:
        xyz = _read_binary_body(data, header)
    finite = np.isfinite(xyz).all(axis=1)
    dropped = int(finite.size - np.count_nonzero(finite))
    if dropped and not drop_non_finite:
        first = int(np.argmin(finite))
        raise CloudFileError(
            f"vertex {first} has a non-finite coordinate {tuple(xyz[first].tolist())} "
            "(drop_non_finite=True reads the file without such points)"
        )
    return PointCloud(
        xyz[finite] if dropped else xyz,
        header.comments,
        header.obj_info,
        header.origins_m,
        dropped,
    )


def _read_ascii_body(data: bytes, header: PlyHeader) -> FloatArray:
    """One line per element (blank lines ignored): the vertices' x, y, z, the rest checked."""
    try:
        text = data[header.body_start :].decode("ascii")
    except UnicodeDecodeError as exc:
        offset = header.body_start + exc.start
        line_no = header.line_count + 1 + data.count(b"\n", header.body_start, offset)
        raise CloudFileError(
            f"line {line_no}: a byte that is not ASCII (offset {offset})"
        ) from None
    numbered = enumerate(text.split("\n"), start=header.line_count + 1)
    rows = [(line_no, tokens) for line_no, line in numbered if (tokens := line.split())]
    cursor = 0
    xyz = np.empty((0, 3))
    for element in header.elements:
        if not element.properties:
            continue
        chunk = rows[cursor : cursor + element.count]
        cursor += len(chunk)
        if len(chunk) < element.count:
            last = rows[-1][0] if rows else header.line_count
            raise CloudFileError(
                f"the file ends after line {last}, before element "
                f"{element.name!r} index {len(chunk)} of {element.count}"
            )
        if element.name == "vertex" and not element.has_lists:
            xyz = _ascii_vertex_block(chunk, element)
        else:
            values = [_ascii_row(t, element, n, i) for i, (n, t) in enumerate(chunk)]
            if element.name == "vertex":
                xyz = np.array(values, dtype=np.float64).reshape(-1, 3)
    if cursor < len(rows):
        raise CloudFileError(f"line {rows[cursor][0]}: data after the last element")
    return xyz


def _ascii_vertex_block(chunk: list[tuple[int, list[str]]], element: PlyElement) -> FloatArray:
    """Every vertex line at once through numpy (the slow path only to say where it failed)."""
    width = len(element.properties)
    for index, (line_no, tokens) in enumerate(chunk):
        if len(tokens) != width:
            _ascii_row(tokens, element, line_no, index)  # raises, naming the line
    try:
        table = np.array([tokens for _, tokens in chunk], dtype=np.float64).reshape(-1, width)
    except (ValueError, OverflowError):
        table = None
    integer_columns = [i for i, p in enumerate(element.properties) if p.type_char not in "fd"]
    if table is None or not _whole(table[:, integer_columns]):
        for index, (line_no, tokens) in enumerate(chunk):
            _ascii_row(tokens, element, line_no, index)  # raises at the first bad line
        table = np.array([[float(t) for t in tokens] for _, tokens in chunk]).reshape(-1, width)
    columns = [next(i for i, p in enumerate(element.properties) if p.name == a) for a in "xyz"]
    return table[:, columns]


def _whole(values: FloatArray) -> bool:
    return bool(np.isfinite(values).all() and np.equal(np.floor(values), values).all())


def _ascii_row(tokens: list[str], element: PlyElement, line_no: int, index: int) -> list[float]:
    """Check one ascii element line; its x, y, z if it is a vertex."""
    where = f"line {line_no} (element {element.name!r} index {index})"
    found: dict[str, float] = {}
    position = 0
    for prop in element.properties:
        if prop.count_char is not None:
            if position >= len(tokens) or not INTEGER.fullmatch(tokens[position]):
                raise CloudFileError(f"{where}: list {prop.name!r} needs a length")
            length = int(tokens[position])
            if length < 0:
                raise CloudFileError(f"{where}: list {prop.name!r} has length {length}")
            position += 1
            items = tokens[position : position + length]
            if len(items) < length:
                raise CloudFileError(f"{where}: too few values for list {prop.name!r}")
            for item in items:
                _ascii_number(item, prop, where)
            position += length
        elif position >= len(tokens):
            raise CloudFileError(f"{where}: too few values (no {prop.name!r})")
        else:
            found[prop.name] = _ascii_number(tokens[position], prop, where)
            position += 1
    if position != len(tokens):
        raise CloudFileError(f"{where}: too many values ({len(tokens)}, expected {position})")
    return [found[axis] for axis in "xyz"] if element.name == "vertex" else []


def _ascii_number(token: str, prop: PlyProperty, where: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise CloudFileError(f"{where}: {token[:40]!r} is not a number ({prop.name!r})") from None
    if prop.type_char not in "fd" and not value.is_integer():
        raise CloudFileError(f"{where}: {token[:40]!r} is not an integer ({prop.name!r})")
    return value


def _read_binary_body(data: bytes, header: PlyHeader) -> FloatArray:
    """Each element in turn: a structured-dtype view when its rows have a fixed size,
    property by property when they hold lists (whose lengths are in the data)."""
    offset = header.body_start
    xyz = np.empty((0, 3))
    for element in header.elements:
        if element.has_lists:
            offset, rows = _binary_rows(data, offset, element, header.encoding)
            if element.name == "vertex":
                xyz = np.array(rows, dtype=np.float64).reshape(-1, 3)
            continue
        fields = [
            (f"p{i}", header.encoding + p.type_char) for i, p in enumerate(element.properties)
        ]
        row_type = np.dtype(fields)
        end = offset + element.count * row_type.itemsize
        if end > len(data):
            index = (len(data) - offset) // row_type.itemsize
            raise _truncated(data, offset + index * row_type.itemsize, element, index)
        if element.name == "vertex" and element.count:
            block = np.frombuffer(data, row_type, element.count, offset)
            names = [p.name for p in element.properties]
            xyz = np.column_stack([block[f"p{names.index(axis)}"] for axis in "xyz"])
            xyz = xyz.astype(np.float64)
        offset = end
    if offset != len(data):
        raise CloudFileError(
            f"{len(data) - offset} bytes of extra data after the body (from byte offset {offset})"
        )
    return xyz


def _binary_rows(
    data: bytes, offset: int, element: PlyElement, endian: str
) -> tuple[int, list[list[float]]]:
    """Walk rows with lists; a vertex's x, y, z as rows, nothing for other elements."""
    formats = [
        (p, struct.Struct(endian + p.type_char), struct.Struct(endian + (p.count_char or "B")))
        for p in element.properties
    ]
    rows: list[list[float]] = []
    for index in range(element.count):
        found: dict[str, float] = {}
        for prop, value_format, count_format in formats:
            if prop.count_char is None:
                found[prop.name] = _unpack(data, offset, value_format, element, index)
                offset += value_format.size
                continue
            length = int(_unpack(data, offset, count_format, element, index))
            if length < 0:
                raise CloudFileError(
                    f"byte offset {offset} (element {element.name!r} index {index}): "
                    f"list {prop.name!r} has length {length}"
                )
            offset += count_format.size + length * value_format.size
            if offset > len(data):
                raise _truncated(data, offset - length * value_format.size, element, index)
        if element.name == "vertex":
            rows.append([found[axis] for axis in "xyz"])
    return offset, rows


def _unpack(data: bytes, offset: int, fmt: struct.Struct, element: PlyElement, index: int) -> float:
    if offset + fmt.size > len(data):
        raise _truncated(data, offset, element, index)
    return float(fmt.unpack_from(data, offset)[0])


def _truncated(data: bytes, offset: int, element: PlyElement, index: int) -> CloudFileError:
    return CloudFileError(
        f"the body is truncated at byte offset {offset} of {len(data)}: "
        f"element {element.name!r} index {index} of {element.count} is incomplete"
    )


def write_ply(
    cloud_xyz_m: npt.ArrayLike,
    *,
    binary: bool = True,
    double: bool = False,
    big_endian: bool = False,
    comments: Iterable[str] = (),
    obj_info: Iterable[str] = (),
    origins_m: Iterable[Sequence[float]] = (),
) -> bytes:
    """``cloud_xyz_m`` (N, 3) as a PLY file that `parse_ply` reads back.

    Binary little-endian by default (``big_endian`` for the other order): a fifth of the
    bytes of ascii, and nothing to parse. Coordinates are ``float`` (float32) unless
    ``double``: float32 keeps 24 bits, i.e. 4 µm at 50 m and 0.1 mm at 1 km from the
    origin, far below a handheld LiDAR's centimetre noise; ``double`` makes the round trip
    exact. Ascii writes the same values (the float32-rounded ones unless ``double``) as
    decimals that read back exactly, so every form reads back to the same numbers.
    Viewpoints go in as ``comment dbw origin X Y Z`` lines, written exactly.
    """
    xyz = _writable_xyz(cloud_xyz_m, double)
    encoding = (
        ("binary_big_endian" if big_endian else "binary_little_endian") if binary else "ascii"
    )
    lines = ["ply", f"format {encoding} 1.0"]
    for text in comments:
        if text.split()[:2] == ORIGIN_COMMENT.split():
            raise CloudFileError(f"comment {text!r} would read back as a viewpoint")
        lines.append("comment " + _one_line(text))
    for text in obj_info:
        lines.append("obj_info " + _one_line(text))
    for origin in origins_m:
        x, y, z = parse_origin([str(v) for v in origin], f"viewpoint {origin!r}")
        lines.append(f"comment {ORIGIN_COMMENT} {x!r} {y!r} {z!r}")
    scalar = "double" if double else "float"
    lines += [f"element vertex {xyz.shape[0]}"] + [f"property {scalar} {a}" for a in "xyz"]
    lines.append("end_header\n")
    try:
        head = "\n".join(lines).encode("utf-8")
    except UnicodeEncodeError as exc:
        raise CloudFileError(f"a comment cannot be written as UTF-8: {exc.reason}") from None
    if binary:
        return (
            head + xyz.astype((">" if big_endian else "<") + ("f8" if double else "f4")).tobytes()
        )
    return head + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in xyz.tolist()).encode("ascii")


def _writable_xyz(cloud_xyz_m: npt.ArrayLike, double: bool) -> FloatArray:
    """The cloud as float64, rounded to float32 unless ``double``; refused if not finite."""
    try:
        xyz = np.asarray(cloud_xyz_m, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CloudFileError(f"a cloud is an (N, 3) array of numbers: {exc}") from None
    if xyz.shape == (0,):  # an empty list: no points
        xyz = xyz.reshape(0, 3)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise CloudFileError(f"a cloud is an (N, 3) array, not {xyz.shape}")
    if not double:
        with np.errstate(over="ignore"):
            xyz = xyz.astype(np.float32).astype(np.float64)
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        first = int(np.argmin(finite))
        raise CloudFileError(
            f"point {first} {tuple(xyz[first].tolist())} is not finite"
            + ("" if double else " as float32 (double=True keeps float64)")
        )
    return xyz


def _one_line(text: str) -> str:
    if "\n" in text or "\r" in text:
        raise CloudFileError(f"a header comment is one line, got {text!r}")
    return text
