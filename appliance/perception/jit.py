"""Compiled kernels: the few loops over a scan's points that numpy cannot make cheap.

The fits run on arcs and boards of a few dozen points, hundreds of times a second, and a
numpy call on such an array costs a microsecond or more before any arithmetic: a circle
search of five steps was ~180 µs of call overhead for ~1 µs of work. numba compiles
these loops (the same Python source; ``NUMBA_DISABLE_JIT=1`` runs it as plain Python),
which puts the features of a scan inside the time the estimator has for it on a small
vehicle PC.

Semantics kept from numpy: ``error_model="numpy"`` (a division by zero gives inf or NaN,
as the numpy code it replaces, and never raises), no fast-math (no reassociation, no fused
multiply-add: sums are taken in order, so a result is the same on every CPU, in the
daemon, in simulation and in replay).

Each kernel is compiled for its declared argument types when its module is imported,
never on a call: a process on a clock never waits for the compiler. Compiled code is
cached on disk (``__pycache__`` beside the source, or the directory ``NUMBA_CACHE_DIR``
names: the systemd unit gives it its cache directory), so only the first start after an
install compiles (~7 s on a slow two-core machine; loading them is under a second).
Where no cache directory is writable, the kernels are compiled at every start instead:
slower to start, the same results.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba
from numba import types

F = TypeVar("F", bound=Callable[..., Any])

# Argument types. Arrays read are read-only of any layout: every float64 array of that
# many dimensions converts to them (C or strided, writable or not), so one compiled
# version serves every caller. Arrays written are writable.
F64 = types.float64
I64 = types.int64
BOOL = types.boolean
IN_1D = types.Array(types.float64, 1, "A", readonly=True)
IN_2D = types.Array(types.float64, 2, "A", readonly=True)
OUT_1D = types.Array(types.float64, 1, "A")
OUT_2D = types.Array(types.float64, 2, "A")
IN_INDEX = types.Array(types.int64, 1, "A", readonly=True)
OUT_INDEX = types.Array(types.int64, 1, "A")
IN_BOOL = types.Array(types.boolean, 1, "A", readonly=True)

_OPTIONS: dict[str, Any] = {"nogil": True, "error_model": "numpy", "fastmath": False}

# Every kernel, for `compiled_signatures`.
KERNELS: list[Any] = []


def kernel(*argument_types: Any) -> Callable[[F], F]:
    """The function compiled for these argument types when it is defined (at import;
    from the cache after the first time). Called with arguments that do not convert to
    them it raises TypeError rather than compiling again: a compilation takes seconds,
    and nothing on a clock may wait for one."""

    def compile_(function: F) -> F:
        try:
            compiled = numba.njit(argument_types, cache=True, **_OPTIONS)(function)
        except RuntimeError:  # "cannot cache function ...: no locator available"
            compiled = numba.njit(argument_types, cache=False, **_OPTIONS)(function)
        KERNELS.append(compiled)
        return cast(F, compiled)

    return compile_


def compiled_signatures() -> dict[str, int]:
    """How many type signatures each kernel is compiled for (one: its own)."""
    return {f"{k.py_func.__module__}.{k.py_func.__qualname__}": len(k.signatures) for k in KERNELS}
