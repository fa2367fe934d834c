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

A kernel compiles on its first call with given argument types (seconds on a small
machine); a process that runs the features on a clock calls `features.warm_up` first
(the localizers do, when they are built), which makes those calls on a made-up scan.
Compiled code is cached on disk (``__pycache__`` beside the source, or the directory
``NUMBA_CACHE_DIR`` names: the systemd unit gives it its cache directory), so only the
first start after an install compiles. Where no cache directory is writable, the kernels
are compiled at every start instead: slower to start, the same results.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba

F = TypeVar("F", bound=Callable[..., Any])

_OPTIONS: dict[str, Any] = {"nogil": True, "error_model": "numpy", "fastmath": False}

# Every kernel, for `compiled_signatures`.
KERNELS: list[Any] = []


def kernel(function: F) -> F:
    """``function`` compiled on its first call for the types it is called with (or
    loaded from the cache): `features.warm_up` makes those calls before a clock runs."""
    try:
        compiled = numba.njit(cache=True, **_OPTIONS)(function)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        compiled = numba.njit(cache=False, **_OPTIONS)(function)
    KERNELS.append(compiled)
    return cast(F, compiled)


def compiled_signatures() -> dict[str, int]:
    """How many type signatures each kernel has been compiled for: a first call with new
    types compiles, which takes seconds, so on a clock there should be none."""
    return {f"{k.py_func.__module__}.{k.py_func.__qualname__}": len(k.signatures) for k in KERNELS}
