"""The worker's map as a list of objects: pallet poses in JSON, read and written without I/O.

The other form a worker's terminal can hand over (Kinouchi et al., section 2.1): instead of
the raw cloud, the pallets it already found, each a pose in the terminal's frame::

    {"frame": "worker",
     "objects": [{"name": "p1", "kind": "1100x1100", "x_m": 1.0, "y_m": 2.0,
                  "yaw_deg": 90.0, "sigma_xy_m": 0.03, "sigma_yaw_deg": 1.0}]}

``kind`` is a `PalletKind` value; the sigmas are optional and default to what a consumer
device achieves (3 cm, 1 deg); the covariance is diag(σxy², σxy², σyaw²). A map this
project wrote (`dbw merge --out`) may give ``covariance_m_rad`` instead: the full 3x3
over (x, y, yaw) in m², m·rad, rad², symmetric and positive semi-definite, and
``seen_by`` ("vehicle" or "worker": who saw the pallet, for a reader). People write
these files by hand, so a misspelled key is refused rather than ignored (``extra``
forbidden, a key given twice refused), names must be unique (the merge reports pallets
by name), and every problem is listed at once with its JSON path (``objects[2].yaw_deg``).

Angles are degrees in the file and radians in the map. Through `math.radians`, about one
float of radians in ten is the image of no float of degrees, so writing a map and reading
it back would turn those pallets by an ulp. Instead the file's decimal text is converted
with a 60-digit π, and `dump_object_map` writes the (shortest) decimal that converts back
to the very same radians: a pose round-trips exactly, whatever its yaw.
"""

from __future__ import annotations

import difflib
import json
import math
from collections import Counter
from collections.abc import Callable
from decimal import Context, Decimal
from typing import Annotated, Any, Literal, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from appliance.mapping.pallets import Pallet, PalletKind, PalletMap

DEFAULT_SIGMA_XY_M = 0.03  # a consumer 3D LiDAR's pallet position, 1 sigma
DEFAULT_SIGMA_YAW_DEG = 1.0
MAX_ABS_XY_M = 10_000.0  # a site, not a unit mistake (mm written as m)
MIN_SIGMA = 1e-6  # below a micrometre / micro-degree a covariance is singular in practice

_PI = Decimal("3.14159265358979323846264338327950288419716939937510582097494459")
_EXACT = Context(prec=60, traps=[])
_SHOWN_PROBLEMS = 50  # a file of a thousand broken objects needs the first few, not a page


class ObjectFileError(ValueError):
    """An object file (or a map to write as one) with every problem found, one per line."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = tuple(problems)
        shown = [f"  - {problem}" for problem in problems[:_SHOWN_PROBLEMS]]
        if len(problems) > _SHOWN_PROBLEMS:
            shown.append(f"  ... and {len(problems) - _SHOWN_PROBLEMS} more")
        super().__init__(f"{len(problems)} problem(s) in the object file:\n" + "\n".join(shown))


def _finite(low: float, high: float) -> Any:
    """A float within bounds, given as a JSON number (not a string, not a boolean)."""
    return Field(ge=low, le=high, allow_inf_nan=False, strict=True)


Coordinate = Annotated[float, _finite(-MAX_ABS_XY_M, MAX_ABS_XY_M)]


class ObjectEntry(BaseModel):
    """One object as the file gives it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1, max_length=128, strict=True)
    kind: PalletKind
    x_m: Coordinate
    y_m: Coordinate
    yaw_deg: Annotated[float, _finite(-360.0, 360.0)]
    sigma_xy_m: Annotated[float, _finite(MIN_SIGMA, 10.0)] = DEFAULT_SIGMA_XY_M
    sigma_yaw_deg: Annotated[float, _finite(MIN_SIGMA, 180.0)] = DEFAULT_SIGMA_YAW_DEG
    covariance_m_rad: (
        Annotated[
            list[
                Annotated[
                    list[Annotated[float, _finite(-1e6, 1e6)]], Field(min_length=3, max_length=3)
                ]
            ],
            Field(min_length=3, max_length=3),
        ]
        | None
    ) = None
    seen_by: Literal["vehicle", "worker"] | None = None

    @model_validator(mode="after")
    def _one_covariance(self) -> Self:
        if self.covariance_m_rad is None:
            return self
        if {"sigma_xy_m", "sigma_yaw_deg"} & self.model_fields_set:
            raise ValueError("give covariance_m_rad or the sigmas, not both")
        matrix = np.array(self.covariance_m_rad)
        scale = float(np.abs(matrix).max()) or 1.0
        if not np.allclose(matrix, matrix.T, rtol=0.0, atol=1e-12 * scale):
            raise ValueError("covariance_m_rad must be symmetric")
        if float(np.linalg.eigvalsh(0.5 * (matrix + matrix.T))[0]) < -1e-12 * scale:
            raise ValueError("covariance_m_rad must be positive semi-definite")
        return self


class ObjectMapFile(BaseModel):
    """The whole file."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    frame: str = Field("worker", min_length=1, max_length=64, strict=True)
    objects: list[ObjectEntry]


def parse_object_map(data: bytes, *, source: str = "") -> PalletMap:
    """The pallets in ``data`` (UTF-8 JSON), or `ObjectFileError` listing every problem."""
    try:
        text = data.decode("utf-8-sig")  # a BOM from a Windows editor is harmless
    except UnicodeDecodeError as exc:
        raise ObjectFileError([f"not UTF-8: byte offset {exc.start} ({exc.reason})"]) from None
    raw = _load_json(text, parse_float=float)
    problems = _repeated_key_problems(raw) + _duplicate_name_problems(raw)
    try:
        model = ObjectMapFile.model_validate(raw)
    except ValidationError as exc:
        problems += _explain(exc)
    if problems:
        raise ObjectFileError(problems)
    # The same text again with its numbers as decimals: the degrees exactly as written.
    written = _load_json(text, parse_float=Decimal)["objects"]
    pallets = []
    for entry, numbers in zip(model.objects, written, strict=True):
        yaw_rad = _radians(Decimal(numbers["yaw_deg"]))
        sigma_yaw_rad = _radians(Decimal(numbers.get("sigma_yaw_deg", DEFAULT_SIGMA_YAW_DEG)))
        covariance = np.diag([entry.sigma_xy_m**2, entry.sigma_xy_m**2, sigma_yaw_rad**2])
        if entry.covariance_m_rad is not None:
            given = np.array(entry.covariance_m_rad)
            covariance = 0.5 * (given + given.T)
        pallets.append(Pallet(entry.x_m, entry.y_m, yaw_rad, covariance, entry.kind, entry.name))
    return PalletMap(tuple(pallets), model.frame, source)


def dump_object_map(pallet_map: PalletMap) -> bytes:
    """``pallet_map`` as an object file that `parse_object_map` reads back to the same floats.

    The file holds a name, a kind, a pose and two sigmas per pallet, so a covariance that
    is not diag(a, a, b) is refused (rather than silently rounded to one), ``support`` and
    ``source`` are not kept, and a map the file could not be read back from (an empty or
    repeated name, a yaw beyond ±360°) is refused with the same messages `parse_object_map`
    gives. A variance that is not the square of a float comes back as the nearest such
    square (an ulp away); everything else comes back exactly.
    """
    problems: list[str] = []
    entries: list[dict[str, Any]] = []
    for index, pallet in enumerate(pallet_map.pallets):
        covariance = pallet.covariance
        variance_xy, variance_yaw = float(covariance[0, 0]), float(covariance[2, 2])
        diagonal = covariance[1, 1] == variance_xy and not covariance[~np.eye(3, dtype=bool)].any()
        if not diagonal or min(variance_xy, variance_yaw) < 0.0:
            problems.append(
                f"objects[{index}] ({pallet.name!r}): an object file holds a covariance "
                f"diag(σxy², σxy², σyaw²), not {covariance.tolist()}"
            )
        entries.append(
            {
                "name": pallet.name,
                "kind": pallet.kind.value,
                "x_m": pallet.x_m,
                "y_m": pallet.y_m,
                "yaw_deg": _degrees(pallet.yaw_rad),
                "sigma_xy_m": math.sqrt(abs(variance_xy)),
                "sigma_yaw_deg": _degrees(math.sqrt(abs(variance_yaw))),
            }
        )
    as_read = {
        "frame": pallet_map.frame,
        "objects": [{k: _plain(v) for k, v in entry.items()} for entry in entries],
    }
    problems += _duplicate_name_problems(as_read)
    try:
        ObjectMapFile.model_validate(as_read)
    except ValidationError as exc:
        problems += _explain(exc)
    if problems:
        raise ObjectFileError(problems)
    rows = ["    {" + ", ".join(_member(k, v) for k, v in e.items()) + "}" for e in entries]
    objects = "[\n" + ",\n".join(rows) + "\n  ]" if rows else "[]"
    frame = json.dumps(pallet_map.frame)
    return f'{{\n  "frame": {frame},\n  "objects": {objects}\n}}\n'.encode("ascii")


def _member(key: str, value: Any) -> str:
    # json.dumps writes floats with repr (exact) and escapes every non-ASCII character,
    # so the file is ASCII whatever the names; decimals go in as their own text.
    text = str(value) if isinstance(value, Decimal) else json.dumps(value)
    return f"{json.dumps(key)}: {text}"


def _plain(value: Any) -> Any:
    return float(value) if isinstance(value, Decimal) else value


def _radians(degrees: Decimal) -> float:
    """Degrees (as written) to the nearest float of radians, through a 60-digit π."""
    return float(_EXACT.divide(_EXACT.multiply(degrees, _PI), 180))


def _degrees(angle_rad: float) -> Decimal:
    """The shortest decimal of degrees that `_radians` turns back into ``angle_rad``:
    first the floats next to `math.degrees` (so 90° stays "90.0"), then the exact value
    rounded to ever more digits (the 40-digit one always converts back)."""
    guess = math.degrees(angle_rad)
    if not math.isfinite(guess):
        return Decimal(guess)  # refused by the validation that follows
    nearby, up, down = [guess], guess, guess
    for _ in range(8):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, -math.inf)
        nearby += [up, down]
    nearby.sort(key=lambda c: (len(repr(c)), abs(c - guess)))
    exact = _EXACT.divide(_EXACT.multiply(Decimal(angle_rad), 180), _PI)
    candidates = [Decimal(repr(c)) for c in nearby]
    candidates += [Context(prec=digits).plus(exact) for digits in range(15, 41)]
    for candidate in candidates:
        back = _radians(candidate)
        if back == angle_rad and math.copysign(1.0, back) == math.copysign(1.0, angle_rad):
            return candidate
    raise AssertionError(f"no decimal of degrees for {angle_rad!r} rad")  # pragma: no cover


def _load_json(text: str, parse_float: Callable[[str], Any]) -> Any:
    try:
        return json.loads(text, parse_float=parse_float, object_pairs_hook=_JsonObject.of)
    except json.JSONDecodeError as exc:
        where = f"line {exc.lineno} column {exc.colno}"
        raise ObjectFileError([f"not JSON: {where}: {exc.msg}"]) from None
    except (ValueError, RecursionError) as exc:  # a 5000-digit integer, [[[[...]]]]
        raise ObjectFileError([f"not JSON this reader takes: {exc}"]) from None


class _JsonObject(dict[str, Any]):
    """A JSON object that remembers the keys it was given more than once."""

    repeated: tuple[str, ...] = ()

    @classmethod
    def of(cls, pairs: list[tuple[str, Any]]) -> _JsonObject:
        node = cls(pairs)
        if len(node) < len(pairs):
            node.repeated = tuple(k for k, n in Counter(k for k, _ in pairs).items() if n > 1)
        return node


def _repeated_key_problems(raw: Any) -> list[str]:
    nodes: list[tuple[tuple[str | int, ...], Any]] = [((), raw)]
    if isinstance(raw, dict) and isinstance(raw.get("objects"), list):
        nodes += [(("objects", i), entry) for i, entry in enumerate(raw["objects"])]
    return [
        f"{_path((*loc, key))}: given more than once (the last one would silently win)"
        for loc, node in nodes
        if isinstance(node, _JsonObject)
        for key in node.repeated
    ]


def _duplicate_name_problems(raw: Any) -> list[str]:
    objects = raw.get("objects") if isinstance(raw, dict) else None
    first: dict[str, int] = {}
    problems = []
    for index, entry in enumerate(objects if isinstance(objects, list) else []):
        name = entry.get("name") if isinstance(entry, dict) else None
        if not isinstance(name, str):
            continue
        if name in first:
            problems.append(
                f"objects[{index}].name: {name!r} is already the name of objects[{first[name]}]"
            )
        else:
            first[name] = index
    return problems


def _explain(exc: ValidationError) -> list[str]:
    """Pydantic's errors as ``path: message (got value)``, unknown keys with a suggestion."""
    problems = []
    for error in exc.errors(include_url=False):
        loc = tuple(error["loc"])
        if error["type"] == "extra_forbidden":
            known = list((ObjectEntry if len(loc) == 3 else ObjectMapFile).model_fields)
            close = difflib.get_close_matches(str(loc[-1]), known, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            problems.append(f"{_path(loc)}: unknown field ({hint}known: {', '.join(known)})")
            continue
        message = _PLAIN_MESSAGES.get(error["type"], str(error["msg"]))
        if error["type"] != "missing" and not isinstance(error.get("input"), dict | list):
            message += f" (got {repr(error.get('input'))[:60]})"
        problems.append(f"{_path(loc)}: {message}")
    return problems


_PLAIN_MESSAGES = {  # pydantic's words for a JSON reader
    "model_type": "should be a JSON object {...}",
    "model_attributes_type": "should be a JSON object {...}",
    "list_type": "should be a JSON list [...]",
}


def _path(loc: tuple[str | int, ...]) -> str:
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path or "(top level)"
