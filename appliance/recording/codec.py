"""An exact, typed JSON codec for what the daemon records: samples, inputs, outputs.

Why not pickle: a recording is read long after, on another machine, often because
something went wrong; unpickling a file runs whatever it names, so a corrupt or hostile
recording could do anything. Why not plain ``json.dumps(asdict(...))``: replay must
rebuild the very objects the core saw (enums, frozen dataclasses, named tuples, raw
scanner arrays) and reproduce its outputs bit for bit, so every float must come back
identical and every value as its own type. This codec walks the declared field types:

- floats are JSON numbers (``repr`` round-trips exactly); non-finite ones, which JSON
  has no number for and Foxglove would refuse, are the strings ``"inf"``, ``"-inf"``,
  ``"nan"``;
- enums and flags are their values; dataclasses and named tuples are objects of their
  init fields; tuples and lists are arrays; mappings are objects with string keys;
- numpy arrays are ``{"dtype", "shape", "b64"}``: the raw bytes, little-endian, exact
  and a third the size of a list of numbers;
- a union of several classes (``GnssPose | GnssNoFix``) carries ``"_type"``.

Decoding checks what it reads against the declared type and raises `CodecError`, one
exception type, for anything else, so a damaged file gives a clear message and never a
half-built object. ``Any`` (the free-form fields of a log note) is plain JSON both ways.
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import math
import sys
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

JsonValue = Any  # what json.dumps accepts and json.loads returns

_NON_FINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}
# Arrays in a recording are scanner channels and small vectors; this bounds what a
# damaged or hostile file can make the reader allocate.
MAX_ARRAY_BYTES = 16 * 1024 * 1024
# One-byte types have no byte order: numpy writes them "|u1", "|i1", "|b1".
_DTYPES = frozenset(
    {"<u1", "<u2", "<u4", "<i1", "<i2", "<i4", "<i8", "<f4", "<f8", "|b1", "|u1", "|i1"}
)


class CodecError(ValueError):
    """A value that does not fit its declared type (on either side of the codec)."""


def encode(value: Any, declared: Any = Any) -> JsonValue:
    """``value`` as JSON-able data, exact for its declared type (``Any``: its own)."""
    if declared is Any:
        return _encode_free(value)
    origin = typing.get_origin(declared)
    if origin is typing.Union or origin is types.UnionType:
        return _encode_union(value, typing.get_args(declared))
    if declared is type(None):
        if value is not None:
            raise CodecError(f"expected None, got {type(value).__name__}")
        return None
    if origin is None and isinstance(declared, type):
        return _encode_class(value, declared)
    if origin is tuple:
        return _encode_tuple(value, typing.get_args(declared))
    if origin in (list, Sequence):
        (item,) = typing.get_args(declared) or (Any,)
        return [encode(v, item) for v in value]
    if origin in (dict, Mapping):
        _, item = typing.get_args(declared) or (str, Any)
        return {_key(k): encode(v, item) for k, v in value.items()}
    if origin is np.ndarray:
        return _encode_array(value)
    if origin is typing.Literal:
        return value
    raise CodecError(f"cannot encode declared type {declared!r}")


def decode(data: JsonValue, declared: Any) -> Any:
    """The object ``data`` encodes as ``declared``; `CodecError` if it does not fit."""
    try:
        return _decode(data, declared)
    except CodecError:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, OverflowError) as exc:
        raise CodecError(f"{declared!r}: {exc}") from exc


def _key(key: Any) -> str:
    if not isinstance(key, str):
        raise CodecError(f"mapping keys must be strings, got {type(key).__name__}")
    return key


def _encode_float(value: float) -> JsonValue:
    if math.isfinite(value):
        return float(value)
    return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")


def _encode_free(value: Any) -> JsonValue:
    """A value of no declared type: JSON for what JSON has, a best effort for the rest."""
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, enum.Enum):
        return _encode_free(value.value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return _encode_float(float(value))
    if isinstance(value, Mapping):
        return {str(k): _encode_free(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_encode_free(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _encode_class(value, type(value))
    if isinstance(value, np.ndarray):
        return [_encode_free(v) for v in value.tolist()]
    return str(value)


def _encode_union(value: Any, arms: tuple[Any, ...]) -> JsonValue:
    if value is None:
        if type(None) not in arms:
            raise CodecError("None where the type does not allow it")
        return None
    classes = [a for a in arms if a is not type(None)]
    if len(classes) == 1:
        return encode(value, classes[0])
    for arm in classes:
        if isinstance(arm, type) and type(value) is arm:
            encoded = encode(value, arm)
            if isinstance(encoded, dict):
                return {"_type": arm.__name__, **encoded}
            return encoded
    for arm in classes:  # plain values in a union of plain types (int | float, ...)
        if isinstance(arm, type) and isinstance(value, arm):
            return encode(value, arm)
    raise CodecError(f"{type(value).__name__} is none of {arms!r}")


def _encode_class(value: Any, cls: type) -> JsonValue:
    if cls is bool:
        return bool(_check(value, bool))
    if cls is int:
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise CodecError(f"expected int, got {type(value).__name__}")
        return int(value)
    if cls is float:
        if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
            raise CodecError(f"expected float, got {type(value).__name__}")
        return _encode_float(float(value))
    if cls is str:
        return _check(value, str)
    if issubclass(cls, enum.Enum):
        return _check(value, cls).value
    if cls is np.ndarray:
        return _encode_array(value)
    fields = _fields(cls)
    if fields is None:
        raise CodecError(f"cannot encode {cls.__name__}: not a dataclass or named tuple")
    _check(value, cls)
    return {name: encode(getattr(value, name), hint) for name, hint in fields}


def _check(value: Any, cls: type) -> Any:
    if not isinstance(value, cls):
        raise CodecError(f"expected {cls.__name__}, got {type(value).__name__}")
    return value


def _encode_tuple(value: Any, args: tuple[Any, ...]) -> JsonValue:
    if not isinstance(value, tuple):
        raise CodecError(f"expected a tuple, got {type(value).__name__}")
    if len(args) == 2 and args[1] is Ellipsis:
        return [encode(v, args[0]) for v in value]
    if len(args) != len(value):
        raise CodecError(f"expected {len(args)} items, got {len(value)}")
    return [encode(v, a) for v, a in zip(value, args, strict=True)]


def _encode_array(value: Any) -> JsonValue:
    array = np.asarray(value)
    little = array.astype(array.dtype.newbyteorder("<"), copy=False)
    if little.dtype.str not in _DTYPES:  # what decode would refuse: say so now, not at replay
        raise CodecError(f"array dtype {little.dtype.str!r} is not one a recording holds")
    return {
        "dtype": little.dtype.str,
        "shape": list(little.shape),
        "b64": base64.b64encode(np.ascontiguousarray(little).tobytes()).decode("ascii"),
    }


_FIELDS: dict[type, tuple[tuple[str, Any], ...] | None] = {}


def _fields(cls: type) -> tuple[tuple[str, Any], ...] | None:
    """The init fields of a dataclass or named tuple with their resolved types (cached)."""
    if cls not in _FIELDS:
        _FIELDS[cls] = _resolve_fields(cls)
    return _FIELDS[cls]


def _resolve_fields(cls: type) -> tuple[tuple[str, Any], ...] | None:
    module = sys.modules.get(cls.__module__)
    namespace = dict(vars(module)) if module is not None else {}
    try:
        hints = typing.get_type_hints(cls, globalns=namespace)
    except NameError as exc:
        raise CodecError(f"cannot resolve the field types of {cls.__name__}: {exc}") from exc
    if dataclasses.is_dataclass(cls):
        return tuple((f.name, hints[f.name]) for f in dataclasses.fields(cls) if f.init)
    named = getattr(cls, "_fields", None)
    if issubclass(cls, tuple) and named is not None:
        return tuple((name, hints.get(name, Any)) for name in named)
    return None


def _decode(data: JsonValue, declared: Any) -> Any:
    if declared is Any:
        return data
    origin = typing.get_origin(declared)
    if origin is typing.Union or origin is types.UnionType:
        return _decode_union(data, typing.get_args(declared))
    if declared is type(None):
        if data is not None:
            raise CodecError(f"expected null, got {data!r:.40}")
        return None
    if origin is None and isinstance(declared, type):
        return _decode_class(data, declared)
    if origin is tuple:
        args = typing.get_args(declared)
        items = _list(data)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_decode(v, args[0]) for v in items)
        if len(args) != len(items):
            raise CodecError(f"expected {len(args)} items, got {len(items)}")
        return tuple(_decode(v, a) for v, a in zip(items, args, strict=True))
    if origin in (list, Sequence):
        (item,) = typing.get_args(declared) or (Any,)
        return [_decode(v, item) for v in _list(data)]
    if origin in (dict, Mapping):
        _, item = typing.get_args(declared) or (str, Any)
        return {_key(k): _decode(v, item) for k, v in _object(data).items()}
    if origin is np.ndarray:
        return _decode_array(data)
    if origin is typing.Literal:
        if data not in typing.get_args(declared):
            raise CodecError(f"{data!r:.40} is not one of {typing.get_args(declared)}")
        return data
    raise CodecError(f"cannot decode declared type {declared!r}")


def _list(data: JsonValue) -> list[Any]:
    if not isinstance(data, list):
        raise CodecError(f"expected an array, got {type(data).__name__}")
    return data


def _object(data: JsonValue) -> dict[str, Any]:
    if not isinstance(data, dict):
        raise CodecError(f"expected an object, got {type(data).__name__}")
    return data


def _decode_union(data: JsonValue, arms: tuple[Any, ...]) -> Any:
    if data is None:
        if type(None) not in arms:
            raise CodecError("null where the type does not allow it")
        return None
    classes = [a for a in arms if a is not type(None)]
    if len(classes) == 1:
        return _decode(data, classes[0])
    if isinstance(data, dict) and "_type" in data:
        for arm in classes:
            if isinstance(arm, type) and arm.__name__ == data["_type"]:
                return _decode({k: v for k, v in data.items() if k != "_type"}, arm)
        raise CodecError(f"_type {data['_type']!r:.40} is none of {arms!r}")
    for arm in classes:
        try:
            return _decode(data, arm)
        except CodecError:
            continue
    raise CodecError(f"{data!r:.40} is none of {arms!r}")


def _decode_class(data: JsonValue, cls: type) -> Any:
    if cls is bool:
        if not isinstance(data, bool):
            raise CodecError(f"expected a boolean, got {data!r:.40}")
        return data
    if cls is int:
        if isinstance(data, bool) or not isinstance(data, int):
            raise CodecError(f"expected an integer, got {data!r:.40}")
        return data
    if cls is float:
        if isinstance(data, str) and data in _NON_FINITE:
            return _NON_FINITE[data]
        if isinstance(data, bool) or not isinstance(data, int | float):
            raise CodecError(f"expected a number, got {data!r:.40}")
        return float(data)
    if cls is str:
        if not isinstance(data, str):
            raise CodecError(f"expected a string, got {data!r:.40}")
        return data
    if issubclass(cls, enum.Enum):
        try:
            return cls(data)
        except ValueError as exc:
            raise CodecError(f"{data!r:.40} is not a {cls.__name__}") from exc
    if cls is np.ndarray:
        return _decode_array(data)
    fields = _fields(cls)
    if fields is None:
        raise CodecError(f"cannot decode {cls.__name__}: not a dataclass or named tuple")
    obj = _object(data)
    unknown = set(obj) - {name for name, _ in fields}
    if unknown:
        raise CodecError(f"{cls.__name__} has no field {sorted(unknown)[0]!r}")
    kwargs = {name: _decode(obj[name], hint) for name, hint in fields if name in obj}
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise CodecError(f"{cls.__name__}: {exc}") from exc


def _decode_array(data: JsonValue) -> np.ndarray[Any, Any]:
    obj = _object(data)
    dtype, shape, b64 = obj.get("dtype"), obj.get("shape"), obj.get("b64")
    if dtype not in _DTYPES:
        raise CodecError(f"array dtype {dtype!r:.20} is not one a recording holds")
    if not isinstance(shape, list) or not all(
        isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape
    ):
        raise CodecError("array shape must be a list of non-negative integers")
    if not isinstance(b64, str):
        raise CodecError("array data must be base64 text")
    count = math.prod(shape)
    if count * np.dtype(dtype).itemsize > MAX_ARRAY_BYTES:
        raise CodecError(f"array of {count} items is larger than a recording holds")
    try:
        raw = base64.b64decode(b64, validate=True)
    except ValueError as exc:
        raise CodecError(f"array data is not base64: {exc}") from exc
    if len(raw) != count * np.dtype(dtype).itemsize:
        raise CodecError(f"array data has {len(raw)} bytes for shape {shape} of {dtype}")
    array = np.frombuffer(raw, dtype=dtype).reshape(shape)
    native = array.astype(array.dtype.newbyteorder("="), copy=False)
    native.flags.writeable = False
    return native
