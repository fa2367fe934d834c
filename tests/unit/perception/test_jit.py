"""The compiled kernels (`appliance.perception.jit`): warmed up before a clock runs, and
the same results as their source run as plain Python."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from appliance.localization.launcher_localizer import LauncherLocalizer, ScannerSetup
from appliance.perception.jit import compiled_signatures
from appliance.sim import load_site

from .scenes import MOUNTS, SENSOR_ANGLES, render, vehicle_before_board


def test_every_kernel_is_compiled_once_at_import_and_localizing_adds_none() -> None:
    """A compilation takes seconds: in the daemon that would be a stalled scan. Every
    kernel is compiled for its one signature when imported, and from far out to the
    board (the first pose from whole scans, then tracking in regions of interest, the
    arrays as the scans and the fits make them) nothing calls for another."""
    before = compiled_signatures()
    assert before and set(before.values()) == {1}, before
    site = load_site("launcher")
    poses = 0
    for step, distance_m in enumerate((10.0, 5.0, 2.0, 1.0, 0.4)):
        localizer = LauncherLocalizer({n: ScannerSetup(m) for n, m in MOUNTS.items()})
        vehicle = vehicle_before_board(distance_m, 0.1, 1.0)
        for pair in range(4):
            for k, (name, mount) in enumerate(MOUNTS.items()):
                t_s = 0.04 * pair + 0.02 * k
                scan = render(site, vehicle, mount, seed=10 * step + 2 * pair + k, t_s=t_s)
                localizer.update(name, scan, SENSOR_ANGLES, t_s, t_s)
        poses += localizer.estimate(0.2).centre_pose is not None
    assert compiled_signatures() == before
    assert poses >= 4  # it localized: the kernels ran on real work


def test_a_kernel_called_with_the_wrong_types_refuses_rather_than_compiles() -> None:
    from appliance.perception.circle_search import residuals

    with pytest.raises(TypeError, match="No matching definition"):
        residuals(np.arange(3), np.arange(3), 0.0, 0.0, 1.0)  # integer arrays
    assert residuals(np.arange(3.0)[::-1], np.zeros(3), 0.0, 0.0, 1) == pytest.approx(
        [1.0, 0.0, -1.0]
    )  # strided, an integer radius: converted


_SCRIPT = """
import json, numpy as np
from appliance.perception.circles import fit_circle_free, fit_circle_known_radius
from appliance.perception.circles import free_radius_mismatch
from appliance.perception.features import extract_features
from appliance.perception.types import ScannerModel
from drivers.geometry import Pose2D
rng = np.random.default_rng(3)
out = []
for n in (5, 12, 40):
    phi = np.pi + np.linspace(-0.8, 0.8, n)
    xy = np.column_stack([4 + 0.15 * np.cos(phi), 0.3 + 0.15 * np.sin(phi)])
    xy += rng.normal(0, 0.01, xy.shape)
    known = fit_circle_known_radius(xy, 0.15, (0.0, 0.0), ScannerModel())
    free = fit_circle_free(xy, (0.0, 0.0), ScannerModel())
    out.append([known.cx_m, known.cy_m, *known.covariance.ravel().tolist(), free.radius_m,
                free.radius_sigma_m, free_radius_mismatch(xy, known, (0.0, 0.0),
                ScannerModel(), 0.001, 0.0)])
angles = np.linspace(-0.75 * np.pi, 0.75 * np.pi, 1081)
c, s = np.cos(angles), np.sin(angles)
with np.errstate(divide="ignore", invalid="ignore"):
    board = np.where((c > 0) & (np.abs(4 * s / c) <= 1.5), 4 / c, np.inf)
    gap = (3 * c) ** 2 - (9 - 0.15**2)  # a cylinder 3 m ahead, the nearer root
    cylinder = np.where(gap >= 0, 3 * c - np.sqrt(gap), np.inf)
hit = np.flatnonzero(np.isfinite(cylinder))
cylinder[hit[0] - 1], cylinder[hit[-1] + 1] = cylinder[hit[0]], cylinder[hit[-1]]  # footprint
ranges = np.fmin(board, cylinder)
ranges = np.where(np.isfinite(ranges), ranges + 0.004 * np.sin(np.arange(1081) * 1.7), 0.0)
found = extract_features(ranges, angles, Pose2D(0.1, 0.2, 0.3))
assert len(found.circles) == 1 and len(found.lines) >= 1
out.append([[f.r_m, f.alpha_rad, *f.covariance.ravel().tolist()] for f in found.lines])
out.append([[f.cx_m, f.cy_m, f.rms_m] for f in found.circles])
rejections = sorted(found.rejections.items())
from appliance.sim import load_site, render_scan
from appliance.sim.scanner_errors import draw_scanner_errors
for pose in ((-9.0, 0.4, 0.1), (-3.0, -1.0, -0.3)):  # the simulator's cast and echo kernels
    scan, remission = render_scan(load_site("launcher"), 2.0, pose, (2.6, 1.1, 0.8),
                                  rng=np.random.default_rng(1),
                                  errors=draw_scanner_errors(5, 0, True))
    out.append([scan.tolist(), remission.tolist()])
out.append(rejections)
print(json.dumps(out))
"""


def _run(disable_jit: bool) -> object:
    env = dict(os.environ, NUMBA_DISABLE_JIT="1" if disable_jit else "0")
    done = subprocess.run(
        [sys.executable, "-c", _SCRIPT], env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_compiled_and_plain_python_agree() -> None:
    """The kernels' source run as Python (``NUMBA_DISABLE_JIT=1``) gives the compiled
    results: no semantics were left to the compiler (divisions, NaN, integer types)."""
    compiled, plain = _run(False), _run(True)
    assert _flatten(plain) == pytest.approx(_flatten(compiled), rel=1e-12, abs=1e-15)
    assert compiled[-1] == plain[-1]  # the same rejections


def _flatten(value: object) -> list[float]:
    if isinstance(value, list):
        return [x for item in value for x in _flatten(item)]
    if isinstance(value, str):
        return []
    return [float("nan") if value is None else float(value)]  # type: ignore[arg-type]
