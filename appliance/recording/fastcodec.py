"""The encoder of `codec.py`, compiled once per type: what the recorder and replay run.

`codec.encode` and `codec.decode` walk a value's declared type on every call (type hints,
``typing.get_origin``, one ``isinstance`` per branch); a replay decodes a cycle's inputs
fifty times a second of recording and spent most of its time there. Here each declared
type becomes a closure once (`encoder_for`; the decoding side is `fastdecode.py`'s
`decoder_for`) that does only the work that value needs. The format and every check are
the same: `codec.py` stays the reference, and the tests hold these to it on real objects
and on arbitrary JSON (same output, same refusals).
"""

from __future__ import annotations

import enum
import math
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from appliance.recording.codec import (
    CodecError,
    JsonValue,
    _encode_array,
    _encode_free,
    _fields,
)

Encoder = Callable[[Any], JsonValue]

_ENCODERS: dict[Any, Encoder] = {}


def encode_fast(value: Any, declared: Any) -> JsonValue:
    return encoder_for(declared)(value)


def encoder_for(declared: Any) -> Encoder:
    found = _ENCODERS.get(declared)
    if found is None:
        # A placeholder first: a type that refers to itself finds its own encoder.
        _ENCODERS[declared] = lambda value: _ENCODERS[declared](value)
        found = _ENCODERS[declared] = _build_encoder(declared)
    return found


# ---- encoders ------------------------------------------------------------------------


def _float(value: Any) -> JsonValue:
    if value.__class__ is float:
        return value if value - value == 0.0 else _non_finite(value)
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
        raise CodecError(f"expected float, got {type(value).__name__}")
    value = float(value)
    return value if math.isfinite(value) else _non_finite(value)


def _non_finite(value: float) -> str:
    return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")


def _int(value: Any) -> JsonValue:
    if value.__class__ is int:
        return value
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise CodecError(f"expected int, got {type(value).__name__}")
    return int(value)


def _checker(cls: type) -> Encoder:
    def check(value: Any) -> JsonValue:
        if not isinstance(value, cls):
            raise CodecError(f"expected {cls.__name__}, got {type(value).__name__}")
        return value

    return check


def _build_encoder(declared: Any) -> Encoder:
    if declared is Any:
        return _encode_free
    origin = typing.get_origin(declared)
    if origin is typing.Union or origin is types.UnionType:
        return _union_encoder(typing.get_args(declared))
    if declared is type(None):

        def none(value: Any) -> JsonValue:
            if value is not None:
                raise CodecError(f"expected None, got {type(value).__name__}")
            return None

        return none
    if origin is None and isinstance(declared, type):
        return _class_encoder(declared)
    if origin is tuple:
        return _tuple_encoder(typing.get_args(declared))
    if origin in (list, Sequence):
        (item,) = typing.get_args(declared) or (Any,)
        each = encoder_for(item)
        return lambda value: [each(v) for v in value]
    if origin in (dict, Mapping):
        _, item = typing.get_args(declared) or (str, Any)
        each = encoder_for(item)

        def mapping(value: Any) -> JsonValue:
            out = {}
            for k, v in value.items():
                if not isinstance(k, str):
                    raise CodecError(f"mapping keys must be strings, got {type(k).__name__}")
                out[k] = each(v)
            return out

        return mapping
    if origin is np.ndarray:
        return _encode_array
    if origin is typing.Literal:
        return lambda value: value
    raise CodecError(f"cannot encode declared type {declared!r}")


def _class_encoder(cls: type) -> Encoder:
    if cls is bool:
        check = _checker(bool)
        return lambda value: bool(check(value))
    if cls is int:
        return _int
    if cls is float:
        return _float
    if cls is str:
        return _checker(str)
    if issubclass(cls, enum.Enum):
        check = _checker(cls)
        return lambda value: check(value).value
    if cls is np.ndarray:
        return _encode_array
    fields = _fields(cls)
    if fields is None:
        raise CodecError(f"cannot encode {cls.__name__}: not a dataclass or named tuple")
    encoders = tuple((name, encoder_for(hint)) for name, hint in fields)

    def record(value: Any) -> JsonValue:
        if not isinstance(value, cls):
            raise CodecError(f"expected {cls.__name__}, got {type(value).__name__}")
        return {name: each(getattr(value, name)) for name, each in encoders}

    return record


def _tuple_encoder(args: tuple[Any, ...]) -> Encoder:
    if len(args) == 2 and args[1] is Ellipsis:
        each = encoder_for(args[0])

        def homogeneous(value: Any) -> JsonValue:
            if not isinstance(value, tuple):
                raise CodecError(f"expected a tuple, got {type(value).__name__}")
            return [each(v) for v in value]

        return homogeneous
    encoders = tuple(encoder_for(a) for a in args)

    def fixed(value: Any) -> JsonValue:
        if not isinstance(value, tuple):
            raise CodecError(f"expected a tuple, got {type(value).__name__}")
        if len(value) != len(encoders):
            raise CodecError(f"expected {len(encoders)} items, got {len(value)}")
        return [e(v) for e, v in zip(encoders, value, strict=True)]

    return fixed


def _union_encoder(arms: tuple[Any, ...]) -> Encoder:
    nullable = type(None) in arms
    classes = [a for a in arms if a is not type(None)]
    if len(classes) == 1:
        inner = encoder_for(classes[0])

        def optional(value: Any) -> JsonValue:
            if value is None:
                if not nullable:
                    raise CodecError("None where the type does not allow it")
                return None
            return inner(value)

        return optional
    exact = {arm: (arm.__name__, encoder_for(arm)) for arm in classes if isinstance(arm, type)}
    plain = [(arm, encoder_for(arm)) for arm in classes if isinstance(arm, type)]

    def union(value: Any) -> JsonValue:
        if value is None:
            if not nullable:
                raise CodecError("None where the type does not allow it")
            return None
        found = exact.get(type(value))
        if found is not None:
            encoded = found[1](value)
            return {"_type": found[0], **encoded} if isinstance(encoded, dict) else encoded
        for arm, each in plain:
            if isinstance(value, arm):
                return each(value)
        raise CodecError(f"{type(value).__name__} is none of {arms!r}")

    return union
