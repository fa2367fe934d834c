"""A worker's map that misread some pallets' kinds (a cloud's 1.1 m face: a 1100x1100's
side or a 1200x800's long one) merges through the alternative readings of those faces:
they fix the transform, are never added, and a misread pallet on top of one the
vehicle sees is left out."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from appliance.mapping.merge import MergeParams, MergeResult, merge_maps
from appliance.mapping.pallets import Pallet, PalletKind, PalletMap
from drivers.geometry import Pose2D

from .merge_scenes import scene


def _misread(pallet: Pallet, kind: PalletKind, along_m: float) -> Pallet:
    """The pallet as the other kind: its centre moved along its axis by the depths'
    difference (the face is where it is)."""
    c, s = math.cos(pallet.yaw_rad), math.sin(pallet.yaw_rad)
    return replace(pallet, kind=kind, x_m=pallet.x_m + along_m * c, y_m=pallet.y_m + along_m * s)


def test_alternatives_fix_the_transform_and_never_join_the_map() -> None:
    s = scene(np.random.default_rng(5), count=8, seen=4, noise=False)
    other = {PalletKind.EUR: PalletKind.JIS, PalletKind.JIS: PalletKind.EUR}
    # The worker read three of the four pallets the vehicle sees as the other kind.
    misread = [_misread(p, other[p.kind], 0.15) for p in s.worker.pallets[:3]]
    worker = PalletMap((*misread, *s.worker.pallets[3:]), "worker")
    t0 = Pose2D(
        s.worker_in_vehicle.x_m + 0.05, s.worker_in_vehicle.y_m, s.worker_in_vehicle.yaw_rad
    )
    refused = merge_maps(s.vehicle, worker, t0, MergeParams())
    assert not isinstance(refused, MergeResult)  # one common pallet: no merge
    alternatives = tuple(s.worker.pallets[:3]) + tuple(misread)  # each face as each kind
    result = merge_maps(s.vehicle, worker, t0, MergeParams(), alternatives)
    assert isinstance(result, MergeResult), result
    assert np.allclose(result.worker_in_vehicle, s.worker_in_vehicle, atol=1e-9)
    # The vehicle's 4, the worker's 4 it does not see; no alternative, no misreading.
    assert len(result.pallets) == 8
    assert all(
        m.worker_index is not None and m.worker_index < len(worker.pallets) for m in result.added
    )
    assert sorted(m.worker_index for m in result.added if m.worker_index is not None) == [
        4,
        5,
        6,
        7,
    ]
