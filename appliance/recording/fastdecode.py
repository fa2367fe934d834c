"""The decoder of `codec.py`, compiled once per type: what replay runs.

Each declared type becomes a closure once (`decoder_for`) that checks and builds only what
that value needs, as `fastcodec.py` does for encoding (its docstring says why); the
format and every refusal are `codec.decode`'s, which stays the reference the tests hold
this to. Two shortcuts make the same objects with less work: an enum member is looked up
as the enum's constructor would first look it up, and a frozen dataclass whose __init__
only stores its fields gets them stored without the call (`_direct_constructor`).
"""

from __future__ import annotations

import base64
import enum
import inspect
import math
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from appliance.recording.codec import (
    _DTYPES,
    MAX_ARRAY_BYTES,
    CodecError,
    JsonValue,
    _decode_array,
    _fields,
)

Decoder = Callable[[JsonValue], Any]

_DECODERS: dict[Any, Decoder] = {}
_NON_FINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def decode_fast(data: JsonValue, declared: Any) -> Any:
    try:
        return decoder_for(declared)(data)
    except CodecError:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, OverflowError) as exc:
        raise CodecError(f"{declared!r}: {exc}") from exc


def decoder_for(declared: Any) -> Decoder:
    found = _DECODERS.get(declared)
    if found is None:
        # A placeholder first: a type that refers to itself finds its own decoder.
        _DECODERS[declared] = lambda data: _DECODERS[declared](data)
        found = _DECODERS[declared] = _build_decoder(declared)
    return found


def _build_decoder(declared: Any) -> Decoder:
    if declared is Any:
        return lambda data: data
    origin = typing.get_origin(declared)
    if origin is typing.Union or origin is types.UnionType:
        return _union_decoder(typing.get_args(declared))
    if declared is type(None):

        def none(data: JsonValue) -> Any:
            if data is not None:
                raise CodecError(f"expected null, got {data!r:.40}")
            return None

        return none
    if origin is None and isinstance(declared, type):
        return _class_decoder(declared)
    if origin is tuple:
        return _tuple_decoder(typing.get_args(declared))
    if origin in (list, Sequence):
        (item,) = typing.get_args(declared) or (Any,)
        each = decoder_for(item)
        return lambda data: [each(v) for v in _list(data)]
    if origin in (dict, Mapping):
        _, item = typing.get_args(declared) or (str, Any)
        each = decoder_for(item)

        def mapping(data: JsonValue) -> Any:
            out = {}
            for k, v in _object(data).items():
                if not isinstance(k, str):
                    raise CodecError(f"mapping keys must be strings, got {type(k).__name__}")
                out[k] = each(v)
            return out

        return mapping
    if origin is np.ndarray:
        return _decode_vector
    if origin is typing.Literal:
        allowed = typing.get_args(declared)

        def literal(data: JsonValue) -> Any:
            if data not in allowed:
                raise CodecError(f"{data!r:.40} is not one of {allowed}")
            return data

        return literal
    raise CodecError(f"cannot decode declared type {declared!r}")


# Each dtype a recording holds: numpy's object for it, and the same in this machine's order.
_DTYPE_OBJECTS = {name: (np.dtype(name), np.dtype(name).newbyteorder("=")) for name in _DTYPES}


def _decode_vector(data: JsonValue) -> Any:
    """`codec._decode_array` for what a recording holds most, a scanner channel: one
    dimension, the three keys and nothing odd about them, its dtype and its item size
    looked up rather than parsed (a tenth of a scan's decoding). Anything else is left
    to the reference, which says what is wrong with it."""
    if data.__class__ is dict and len(data) == 3:
        dtype, shape, b64 = data.get("dtype"), data.get("shape"), data.get("b64")
        found = _DTYPE_OBJECTS.get(dtype) if dtype.__class__ is str else None
        if found is not None and shape.__class__ is list and len(shape) == 1:
            count, (stored, native) = shape[0], found
            size = count * stored.itemsize if count.__class__ is int and count >= 0 else -1
            if 0 <= size <= MAX_ARRAY_BYTES and b64.__class__ is str:
                try:
                    raw = base64.b64decode(b64, validate=True)
                except ValueError:
                    return _decode_array(data)  # the reference says what is wrong
                if len(raw) == size:
                    array = np.frombuffer(raw, dtype=stored).astype(native, copy=False)
                    array.flags.writeable = False
                    return array
    return _decode_array(data)


def _list(data: JsonValue) -> list[Any]:
    if data.__class__ is not list:
        raise CodecError(f"expected an array, got {type(data).__name__}")
    return data


def _object(data: JsonValue) -> dict[str, Any]:
    if data.__class__ is not dict:
        raise CodecError(f"expected an object, got {type(data).__name__}")
    return typing.cast(dict[str, Any], data)


def _decode_float(data: JsonValue) -> float:
    cls = data.__class__
    if cls is float:
        return typing.cast(float, data)
    if cls is int:
        return float(data)
    if cls is str and data in _NON_FINITE:
        return _NON_FINITE[data]
    raise CodecError(f"expected a number, got {data!r:.40}")


def _decode_int(data: JsonValue) -> int:
    if data.__class__ is not int:
        raise CodecError(f"expected an integer, got {data!r:.40}")
    return data


def _decode_bool(data: JsonValue) -> bool:
    if data.__class__ is not bool:
        raise CodecError(f"expected a boolean, got {data!r:.40}")
    return data


def _decode_str(data: JsonValue) -> str:
    if data.__class__ is not str:
        raise CodecError(f"expected a string, got {data!r:.40}")
    return data


def _class_decoder(cls: type) -> Decoder:
    if cls is bool:
        return _decode_bool
    if cls is int:
        return _decode_int
    if cls is float:
        return _decode_float
    if cls is str:
        return _decode_str
    if issubclass(cls, enum.Enum):
        members = cls._value2member_map_

        def member(data: JsonValue) -> Any:
            # The lookup the enum's own constructor makes first, without the call.
            try:
                return members[data]
            except (KeyError, TypeError):
                pass
            try:
                return cls(data)
            except ValueError as exc:
                raise CodecError(f"{data!r:.40} is not a {cls.__name__}") from exc

        return member
    if cls is np.ndarray:
        return _decode_vector
    fields = _fields(cls)
    if fields is None:
        raise CodecError(f"cannot decode {cls.__name__}: not a dataclass or named tuple")
    decoders = tuple((name, decoder_for(hint)) for name, hint in fields)
    names = frozenset(name for name, _ in fields)
    count = len(decoders)
    direct = _direct_constructor(cls, [name for name, _ in fields])

    def record(data: JsonValue) -> Any:
        obj = _object(data)
        if not names.issuperset(obj):
            unknown = sorted(set(obj) - names)[0]
            raise CodecError(f"{cls.__name__} has no field {unknown!r}")
        if len(obj) == count:  # every field is there
            kwargs = {name: each(obj[name]) for name, each in decoders}
            if direct is not None:
                return direct(kwargs)
        else:
            kwargs = {name: each(obj[name]) for name, each in decoders if name in obj}
        try:
            return cls(**kwargs)
        except TypeError as exc:
            raise CodecError(f"{cls.__name__}: {exc}") from exc

    return record


def _direct_constructor(cls: type, names: list[str]) -> Callable[[dict[str, Any]], Any] | None:
    """How to make an instance of ``cls`` from every field's value without its __init__,
    where that is the same thing: a frozen dataclass whose __init__ is the one dataclasses
    wrote (no __post_init__, no InitVar, no slots, no __new__ of its own) only stores
    each field, one ``object.__setattr__`` call at a time, the largest single cost of
    decoding a cycle's inputs and its scans. The fields go into the instance's __dict__
    in the same order. None for any other class: it is made by calling it."""
    params = getattr(cls, "__dataclass_params__", None)
    init = vars(cls).get("__init__")
    code = getattr(init, "__code__", None)
    if (
        params is None
        or not params.frozen
        or code is None
        or code.co_filename != "<string>"  # written by dataclasses, not in a class body
        or hasattr(cls, "__post_init__")
        or "__slots__" in vars(cls)
        or typing.cast(Any, cls).__new__ is not object.__new__
        or list(inspect.signature(cls).parameters) != names
    ):
        return None
    new = object.__new__

    def direct(values: dict[str, Any]) -> Any:
        instance: Any = new(cls)
        vars(instance).update(values)
        return instance

    return direct


def _tuple_decoder(args: tuple[Any, ...]) -> Decoder:
    if len(args) == 2 and args[1] is Ellipsis:
        each = decoder_for(args[0])
        return lambda data: tuple(each(v) for v in _list(data))
    decoders = tuple(decoder_for(a) for a in args)

    def fixed(data: JsonValue) -> Any:
        items = _list(data)
        if len(items) != len(decoders):
            raise CodecError(f"expected {len(decoders)} items, got {len(items)}")
        return tuple(d(v) for d, v in zip(decoders, items, strict=True))

    return fixed


def _union_decoder(arms: tuple[Any, ...]) -> Decoder:
    nullable = type(None) in arms
    classes = [a for a in arms if a is not type(None)]
    if len(classes) == 1:
        inner = decoder_for(classes[0])

        def optional(data: JsonValue) -> Any:
            if data is None:
                if not nullable:
                    raise CodecError("null where the type does not allow it")
                return None
            return inner(data)

        return optional
    by_name = {arm.__name__: decoder_for(arm) for arm in classes if isinstance(arm, type)}
    in_turn = [decoder_for(arm) for arm in classes]

    def union(data: JsonValue) -> Any:
        if data is None:
            if not nullable:
                raise CodecError("null where the type does not allow it")
            return None
        if isinstance(data, dict) and "_type" in data:
            name = data["_type"]
            each = by_name.get(name) if isinstance(name, str) else None
            if each is None:
                raise CodecError(f"_type {name!r:.40} is none of {arms!r}")
            return each({k: v for k, v in data.items() if k != "_type"})
        for each in in_turn:
            try:
                return each(data)
            except CodecError:
                continue
        raise CodecError(f"{data!r:.40} is none of {arms!r}")

    return union
