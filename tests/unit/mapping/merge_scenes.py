"""Synthetic pallet layouts for the merge tests: one truth in the vehicle map's frame,
the worker's map seen from a floor marker, both with noise."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.mapping.pallets import (
    Pallet,
    PalletKind,
    PalletMap,
    inverse_pose,
    transform_pallet,
)
from drivers.geometry import Pose2D

WORKER_SIGMAS = (0.02, 0.02, math.radians(1.0))
VEHICLE_SIGMAS = (0.01, 0.01, math.radians(0.5))


@dataclass(frozen=True)
class Scene:
    truth: tuple[Pallet, ...]  # in the vehicle map's frame
    vehicle: PalletMap  # the first `seen` of the truth
    worker: PalletMap  # all of the truth, in the worker's frame
    worker_in_vehicle: Pose2D  # the true T0 (the fit's T⁻¹)


def layout(rng: np.random.Generator, count: int, size_m: float = 20.0) -> list[Pallet]:
    """``count`` pallets, centres at least 1.5 m apart, over a square of ``size_m``."""
    centres: list[np.ndarray] = []
    while len(centres) < count:
        centre = rng.uniform(0.0, size_m, 2)
        if all(math.dist(centre, other) >= 1.5 for other in centres):
            centres.append(centre)
    kinds = (PalletKind.JIS, PalletKind.EUR)
    return [
        Pallet(
            float(x),
            float(y),
            float(rng.uniform(-math.pi, math.pi)),
            np.zeros((3, 3)),
            kinds[int(rng.integers(2))],
            f"p{k}",
        )
        for k, (x, y) in enumerate(centres)
    ]


def _noisy(pallet: Pallet, sigmas: tuple[float, float, float], rng: np.random.Generator) -> Pallet:
    noise = rng.normal(0.0, sigmas) if any(sigmas) else np.zeros(3)
    return Pallet(
        pallet.x_m + float(noise[0]),
        pallet.y_m + float(noise[1]),
        pallet.yaw_rad + float(noise[2]),
        np.diag(np.square(np.maximum(sigmas, 1e-4))),
        pallet.kind,
        pallet.name,
    )


def scene(
    rng: np.random.Generator,
    count: int = 10,
    seen: int = 7,
    noise: bool = True,
    worker_in_vehicle: Pose2D | None = None,
) -> Scene:
    truth = tuple(layout(rng, count))
    if worker_in_vehicle is None:
        worker_in_vehicle = Pose2D(
            float(rng.uniform(0.0, 20.0)),
            float(rng.uniform(0.0, 20.0)),
            float(rng.uniform(-math.pi, math.pi)),
        )
    vehicle_in_worker = inverse_pose(worker_in_vehicle)
    zero = (0.0, 0.0, 0.0)
    worker = tuple(
        _noisy(transform_pallet(vehicle_in_worker, p), WORKER_SIGMAS if noise else zero, rng)
        for p in truth
    )
    vehicle = tuple(_noisy(p, VEHICLE_SIGMAS if noise else zero, rng) for p in truth[:seen])
    return Scene(
        truth, PalletMap(vehicle, "vehicle"), PalletMap(worker, "worker"), worker_in_vehicle
    )


def arrays(
    vehicle: PalletMap, worker: PalletMap, pairs: list[tuple[int, int]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """solve_transform's arrays for ``pairs``."""
    v = [vehicle.pallets[i] for i, _ in pairs]
    w = [worker.pallets[j] for _, j in pairs]
    return (
        np.array([(p.x_m, p.y_m) for p in v]),
        np.array([p.yaw_rad for p in v]),
        np.array([(p.x_m, p.y_m) for p in w]),
        np.array([p.yaw_rad for p in w]),
        np.array([p.kind.symmetry_rad for p in v]),
    )
