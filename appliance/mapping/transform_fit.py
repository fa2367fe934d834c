"""The transform that superposes a vehicle's pallet map on a worker's: Kinouchi et al.,
section 2.2 (3), eqs. 1-2, solved for the *global* minimum.

Direction: ``T`` is the paper's. It maps vehicle-map coordinates into the worker's map,
``T q_i ≈ p_i``, so as a pose it is the vehicle map's frame seen in the worker map's
(`TransformFit.vehicle_in_worker`). Its inverse, the worker map's frame in the vehicle
map (what the floor marker gives as ``T0``), is `TransformFit.worker_in_vehicle`.

The derivation, verified here and by the tests against scipy's least squares. With
``R`` the rotation by θ, ``t = (x, y)`` and ``d_i = ψ_i − φ_i``,

    E = 1/2 Σ |R q_i + t − p_i|² + w/2 Σ (θ + d_i)²                          (eq. 1)

``∂E/∂t = 0`` gives ``t = p̄ − R q̄``, the paper's ``x = p̄x − q̄x cosθ + q̄y sinθ``,
``y = p̄y − q̄x sinθ − q̄y cosθ``. With centred ``q'``, ``p'`` what is left is
``E(θ) = const − N (β cosθ − α sinθ) + w/2 Σ (θ + d_i)²`` with

    α = (1/N) Σ (p'x q'y − p'y q'x),   β = (1/N) Σ (p'x q'x + p'y q'y)

(the paper's α and β of eq. 2, written as means of products minus products of means),
and ``dE/dθ = N f(θ)`` with ``f(θ) = ρ sin(θ + γ) + w θ + (w/N) Σ d_i`` where
``ρ = sqrt(α² + β²)`` and ``γ = atan2(α, β)``: the paper's ``arctan(α/β)`` holds only for
``β > 0``; with a vehicle map half a turn from the worker's, ``β < 0``, and only atan2
puts the minimum on the right side. The sign conventions of eq. 2 check out as printed.

Why the global minimum needs care: ``f`` is a sine plus a line, and for ``w`` small next
to ``ρ`` it has several roots (local minima and maxima of E). Newton from one start finds
one of them. Here every local minimum in the interval that must hold the global one is
found and the least E kept (`minimize_angle_rad`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from appliance.mapping.pallets import FloatArray, inverse_pose, posture_difference_rad
from drivers.geometry import Pose2D

# Why this weight: every term of E is then in m², and E is the maximum-likelihood cost
# when w = σ_position² / σ_posture² (per-axis residual spreads). A worker's pallets come
# at about 20 mm and 1° (the noisier of the two maps sets the residuals), so 1° of
# posture weighs as 20 mm of position. The postures matter most when few pallets are
# shared or they stand close together; with ten pallets over 20 m the positions decide
# the angle alone (benchmarks/bench_map_merge.py prints both).
DEFAULT_W_M2_PER_RAD2 = (0.02 / math.radians(1.0)) ** 2

MAX_ITERATIONS = 200  # bisection alone halves a 2π bracket to 1e-15 in about 50 steps
_PAD_RAD = 1e-9  # the search interval is closed; padded so a minimum on its end is inside


@dataclass(frozen=True)
class MergeRefusal:
    """Why there is no transform (or merge): told, never raised."""

    reason: str


@dataclass(frozen=True, eq=False)
class TransformFit:
    """The least-squares ``T`` of eq. 1 and how well it fits.

    ``covariance`` is over ``vehicle_in_worker``'s (x, y, yaw), propagated to first order
    from the pallets' covariances (not estimated from the residuals: with the few pallets
    two maps share, a residual-based spread is itself too uncertain to gate on).
    """

    vehicle_in_worker: Pose2D  # the paper's T: T q_i ≈ p_i; yaw wrapped to [-π, π]
    covariance: FloatArray  # 3x3 over vehicle_in_worker (x, y, yaw)
    cost: float  # E at the minimum (m², the posture term weighted by w)
    position_residuals_m: FloatArray  # (N,) |T q_i − p_i|
    posture_residuals_rad: FloatArray  # (N,) θ + ψ_i − φ_i with the representative used
    iterations: int  # Newton/bisection steps spent on the chosen root
    local_minima: int  # how many local minima of E(θ) were compared

    @property
    def worker_in_vehicle(self) -> Pose2D:
        """``T⁻¹``: the worker map's frame in the vehicle map's."""
        return inverse_pose(self.vehicle_in_worker)

    def worker_in_vehicle_covariance(self) -> FloatArray:
        """The covariance of `worker_in_vehicle`, through the inverse's Jacobian."""
        x, y, yaw = self.vehicle_in_worker
        c, s = math.cos(yaw), math.sin(yaw)
        jacobian = np.array([[-c, -s, s * x - c * y], [s, -c, c * x + s * y], [0.0, 0.0, -1.0]])
        covariance: FloatArray = jacobian @ self.covariance @ jacobian.T
        return covariance


def posture_representatives_rad(
    differences_rad: FloatArray, symmetry_rad: FloatArray, centre_rad: float
) -> FloatArray:
    """Each ``ψ_i − φ_i`` as the value, among those it takes modulo its pallet's symmetry,
    nearest to ``centre_rad``: a square pallet's posture is only known to a quarter turn,
    and eq. 1 needs the one that agrees with the rest."""
    return np.array(
        [
            centre_rad + posture_difference_rad(float(d), centre_rad, float(s))
            for d, s in zip(differences_rad, symmetry_rad, strict=True)
        ],
        dtype=np.float64,
    )


def _root_rad(
    rho: float, gamma: float, w: float, mean_d: float, lo: float, hi: float
) -> tuple[float, int]:
    """The root of ``f`` in ``[lo, hi]``, where ``f`` increases from ``≤ 0`` to ``≥ 0``:
    Newton-Raphson kept inside the bracket, a bisection whenever Newton would leave it."""
    x = 0.5 * (lo + hi)
    for iteration in range(1, MAX_ITERATIONS + 1):
        fx = rho * math.sin(x + gamma) + w * (x + mean_d)
        if fx == 0.0:
            return x, iteration
        if fx < 0.0:
            lo = x
        else:
            hi = x
        slope = rho * math.cos(x + gamma) + w
        step = fx / slope if slope > 0.0 else math.inf
        candidate = x - step
        if not lo < candidate < hi:
            candidate = 0.5 * (lo + hi)
        if abs(candidate - x) <= 4.0 * np.finfo(float).eps * max(1.0, abs(x)):
            return candidate, iteration
        x = candidate
    return x, MAX_ITERATIONS


def minimize_angle_rad(rho: float, gamma: float, w: float, mean_d: float) -> tuple[float, int, int]:
    """The θ of least ``g(θ) = −ρ cos(θ + γ) + w/2 (θ + d̄)²`` (E(θ)/N up to a constant),
    with the Newton steps it took and how many local minima were compared.

    Where to look: every root of ``f = g'`` has ``|w (θ + d̄)| ≤ ρ``. Tighter still, with
    ``θ_k = −γ + 2πk`` the w = 0 angle nearest ``−d̄``, ``g ≥ −ρ + w/2 (θ + d̄)²`` and
    ``g(θ_k) = −ρ + w/2 (θ_k + d̄)²``, so the global minimum has
    ``|θ + d̄| ≤ |θ_k + d̄| ≤ π``. The interval is the intersection of the two.

    Why no root is missed: instead of a uniform grid (which would need a spacing argument
    from ``|f'| ≤ ρ + w`` and ``|f''| ≤ ρ`` and still cannot see a double root), the grid is
    the critical points of ``f`` itself, where ``cos(θ + γ) = −w/ρ``. Between two of them
    ``f`` is monotone, so each cell holds at most one root, and a minimum of E is exactly a
    cell where ``f`` increases through zero. There are at most three such points per 2π.
    """
    if w == 0.0:
        return -gamma, 0, 1
    if rho == 0.0:
        return -mean_d, 0, 1
    centre = -mean_d
    theta_k = -gamma + 2.0 * math.pi * round((centre + gamma) / (2.0 * math.pi))
    radius = min(abs(theta_k - centre), rho / w) + _PAD_RAD * (1.0 + abs(centre))
    lo, hi = centre - radius, centre + radius
    breaks = [lo, hi]
    if w < rho:
        turn = math.acos(-w / rho)
        first = math.floor((lo + gamma - math.pi) / (2.0 * math.pi))
        last = math.ceil((hi + gamma + math.pi) / (2.0 * math.pi))
        for k in range(first, last + 1):
            for u in (turn, -turn):
                theta = u - gamma + 2.0 * math.pi * k
                if lo < theta < hi:
                    breaks.append(theta)
    breaks.sort()

    def f(theta: float) -> float:
        return rho * math.sin(theta + gamma) + w * (theta + mean_d)

    def g(theta: float) -> float:
        return -rho * math.cos(theta + gamma) + 0.5 * w * (theta + mean_d) ** 2

    best: tuple[float, float, int] | None = None  # (g, θ, iterations)
    minima = 0
    for a, b in itertools.pairwise(breaks):
        fa, fb = f(a), f(b)
        if not (fa <= 0.0 <= fb and fa < fb):
            continue
        theta, iterations = _root_rad(rho, gamma, w, mean_d, a, b)
        minima += 1
        if best is None or g(theta) < best[0]:
            best = (g(theta), theta, iterations)
    if best is None:  # only rounding can get here: the w = 0 angle bounds the minimum
        return theta_k, 0, 0
    return best[1], best[2], minima


def _covariance(
    q: FloatArray,
    p: FloatArray,
    theta: float,
    t: FloatArray,
    w: float,
    vehicle_covariance: FloatArray,
    worker_covariance: FloatArray,
) -> FloatArray:
    """First-order covariance of (x, y, θ): at the minimum ``∇E(T, z) = 0``, so
    ``dT/dz = −H⁻¹ ∂²E/∂T∂z`` (the implicit function theorem), with ``H`` the full Hessian
    of E (not Gauss-Newton's: the residuals' curvature term is kept) and ``z`` every
    pallet's (x, y, yaw) in both maps, the pallets independent of one another."""
    c, s = math.cos(theta), math.sin(theta)
    rotation = np.array([[c, -s], [s, c]])
    d_rotation = np.array([[-s, -c], [c, -s]])
    quarter = np.array([[0.0, -1.0], [1.0, 0.0]])  # Rᵀ R'
    n = len(q)
    errors = q @ rotation.T + t - p  # (N, 2): T q_i − p_i
    rq_prime = q @ d_rotation.T  # (N, 2): R' q_i
    hessian = np.zeros((3, 3))
    hessian[0, 0] = hessian[1, 1] = n
    hessian[:2, 2] = hessian[2, :2] = rq_prime.sum(axis=0)
    rq = q @ rotation.T
    hessian[2, 2] = float(np.sum(q * q) - np.sum(rq * errors)) + n * w
    middle = np.zeros((3, 3))
    for i in range(n):
        vehicle_part = np.zeros((3, 3))  # ∂(∇_T E)/∂(q_i, ψ_i)
        vehicle_part[:2, :2] = rotation
        vehicle_part[2, :2] = d_rotation.T @ errors[i] + quarter @ q[i]
        vehicle_part[2, 2] = w
        worker_part = np.zeros((3, 3))  # ∂(∇_T E)/∂(p_i, φ_i)
        worker_part[:2, :2] = -np.eye(2)
        worker_part[2, :2] = -rq_prime[i]
        worker_part[2, 2] = -w
        middle += vehicle_part @ vehicle_covariance[i] @ vehicle_part.T
        middle += worker_part @ worker_covariance[i] @ worker_part.T
    inverse = np.linalg.pinv(hessian)
    covariance: FloatArray = inverse @ middle @ inverse.T
    return 0.5 * (covariance + covariance.T)


def _checked(name: str, value: object, shape: tuple[int, ...]) -> FloatArray | str:
    """``value`` as a finite float array of ``shape`` (-1: any length), or what is wrong."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        return f"{name} is not an array of numbers ({error})"
    expected = tuple(array.shape[0] if size < 0 and array.ndim else size for size in shape)
    if array.shape != expected:
        return f"{name} has shape {array.shape}, not {expected}"
    if not np.isfinite(array).all():
        return f"{name} holds a value that is not finite"
    return array


def solve_transform(
    vehicle_xy_m: FloatArray,
    vehicle_yaw_rad: FloatArray,
    worker_xy_m: FloatArray,
    worker_yaw_rad: FloatArray,
    symmetry_rad: FloatArray,
    w_m2_per_rad2: float = DEFAULT_W_M2_PER_RAD2,
    *,
    min_pairs: int = 2,
    vehicle_covariance: FloatArray | None = None,
    worker_covariance: FloatArray | None = None,
) -> TransformFit | MergeRefusal:
    """The ``T`` (vehicle map into worker map) minimizing eq. 1 over N associated pallets.

    ``symmetry_rad`` is each pair's `PalletKind.symmetry_rad`. Each ``ψ_i − φ_i`` is first
    taken as its representative nearest ``−θ₀``, θ₀ the position-only (w = 0) angle (for
    pallets all at one point, nearest the first pair's); after the fit the representatives
    are chosen again around ``−θ`` and the fit repeated until they stay (each pass can only
    lower E). Covariances are ``(N, 3, 3)`` over each map's (x, y, yaw); ``None`` takes
    that map's poses as exact. One pair is allowed only with ``min_pairs=1`` and ``w > 0``.
    """
    xy_v = _checked("vehicle_xy_m", vehicle_xy_m, (-1, 2))
    if isinstance(xy_v, str):
        return MergeRefusal(xy_v)
    n = xy_v.shape[0]
    zeros = np.zeros((n, 3, 3))
    arrays: list[FloatArray] = []
    for name, value, shape in (
        ("vehicle_yaw_rad", vehicle_yaw_rad, (n,)),
        ("worker_xy_m", worker_xy_m, (n, 2)),
        ("worker_yaw_rad", worker_yaw_rad, (n,)),
        ("symmetry_rad", symmetry_rad, (n,)),
        (
            "vehicle_covariance",
            zeros if vehicle_covariance is None else vehicle_covariance,
            (n, 3, 3),
        ),
        ("worker_covariance", zeros if worker_covariance is None else worker_covariance, (n, 3, 3)),
    ):
        array = _checked(name, value, shape)
        if isinstance(array, str):
            return MergeRefusal(array)
        arrays.append(array)
    yaw_v, xy_w, yaw_w, symmetry, cov_v, cov_w = arrays
    try:
        w = float(w_m2_per_rad2)
    except (TypeError, ValueError):
        return MergeRefusal(f"the posture weight w is not a number: {w_m2_per_rad2!r}")
    if not (math.isfinite(w) and w >= 0.0):
        return MergeRefusal(f"the posture weight w must be finite and >= 0, not {w}")
    if not (symmetry > 0.0).all():
        return MergeRefusal("every pallet's symmetry must be a positive angle")
    if n < max(min_pairs, 1):
        return MergeRefusal(f"{n} associated pallet(s); the fit needs at least {min_pairs}")
    if n == 1 and w == 0.0:
        return MergeRefusal("one pallet's position cannot fix a rotation without its posture")

    mean_q, mean_p = xy_v.mean(axis=0), xy_w.mean(axis=0)
    q_c, p_c = xy_v - mean_q, xy_w - mean_p
    alpha = float(np.mean(p_c[:, 0] * q_c[:, 1] - p_c[:, 1] * q_c[:, 0]))
    beta = float(np.mean(p_c[:, 0] * q_c[:, 0] + p_c[:, 1] * q_c[:, 1]))
    rho, gamma = math.hypot(alpha, beta), math.atan2(alpha, beta)
    spread_q = math.sqrt(float(np.mean(np.sum(q_c**2, axis=1))))
    spread_p = math.sqrt(float(np.mean(np.sum(p_c**2, axis=1))))
    scale = 1.0 + float(max(np.abs(xy_v).max(), np.abs(xy_w).max()))
    degenerate = min(spread_q, spread_p) <= 1e-9 * scale or rho <= 1e-12 * spread_q * spread_p
    if degenerate and w == 0.0:
        return MergeRefusal(
            "the pallets' positions do not fix the rotation (all at one point in one map, "
            "or no rotation matches them) and the postures are not weighed (w = 0)"
        )
    if degenerate:
        rho = 0.0

    differences = yaw_v - yaw_w
    centre = gamma if rho > 0.0 else float(differences[0])  # −θ₀
    best: tuple[float, float, FloatArray, int, int] | None = None
    for _ in range(4):
        d = posture_representatives_rad(differences, symmetry, centre)
        theta, iterations, minima = minimize_angle_rad(rho, gamma, w, float(d.mean()))
        g = -rho * math.cos(theta + gamma) + 0.5 * w * float(np.mean((theta + d) ** 2))
        if best is None or g < best[0]:
            best = (g, theta, d, iterations, minima)
        if np.array_equal(posture_representatives_rad(differences, symmetry, -theta), d):
            break
        centre = -theta
    assert best is not None
    _, theta, d, iterations, minima = best

    c, s = math.cos(theta), math.sin(theta)
    rotation = np.array([[c, -s], [s, c]])
    t = mean_p - rotation @ mean_q
    errors = xy_v @ rotation.T + t - xy_w
    posture_residuals = theta + d
    cost = 0.5 * float(np.sum(errors**2) + w * np.sum(posture_residuals**2))
    covariance = _covariance(xy_v, xy_w, theta, t, w, cov_v, cov_w)
    covariance.flags.writeable = False
    return TransformFit(
        vehicle_in_worker=Pose2D(float(t[0]), float(t[1]), math.remainder(theta, 2.0 * math.pi)),
        covariance=covariance,
        cost=cost,
        position_residuals_m=np.hypot(errors[:, 0], errors[:, 1]),
        posture_residuals_rad=posture_residuals,
        iterations=iterations,
        local_minima=minima,
    )
