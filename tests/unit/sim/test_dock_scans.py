"""`dbw sim dock`'s scans: the forked worker renders the same scans as the inline renderer,
in the same order; a scan reaches the localizer a latency after it was taken; a worker
that fails says why."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from appliance.config import load_config
from appliance.sim.dock_run import DockRunParams, run_dock
from appliance.sim.dock_scans import InlineScans, ScanRenderer, WorkerScans, open_scans
from appliance.sim.scanner_errors import draw_scanner_errors, noise_seed
from appliance.sim.scanner_model import RayCache
from appliance.sim.site_file import load_site
from drivers.geometry import Pose2D
from drivers.lms111.mounted import mount_pose


def _renderer(seed: int = 7) -> ScanRenderer:
    config = load_config("flatbed")
    mounts = {
        "left": mount_pose(config.geometry.scanner_left_mount),
        "right": mount_pose(config.geometry.scanner_right_mount),
    }
    return ScanRenderer(
        load_site("launcher"),
        mounts,
        {name: draw_scanner_errors(seed, i, True) for i, name in enumerate(mounts)},
        {name: np.random.default_rng(noise_seed(seed, i)) for i, name in enumerate(mounts)},
        {name: RayCache() for name in mounts},
        math.radians(0.25),
    )


POSES = [
    ("left", 0.0, Pose2D(-14.0, 0.3, 0.02)),
    ("right", 0.02, Pose2D(-14.0, 0.3, 0.02)),
    ("left", 0.04, Pose2D(-13.99, 0.3, 0.021)),
    ("left", 0.04, Pose2D(-13.99, 0.3, 0.021)),  # the same pose again: from the cache
    ("right", 0.06, Pose2D(-13.5, -0.2, -0.05)),
]


def test_the_worker_renders_what_the_inline_renderer_does_in_order() -> None:
    inline, worker = InlineScans(_renderer()), WorkerScans(_renderer())
    try:
        for name, t_s, pose in POSES:  # all asked for before any is taken
            inline.submit(name, t_s, pose)
            worker.submit(name, t_s, pose)
        for _ in POSES:
            expected, got = inline.take(), worker.take()
            assert got.shape == expected.shape == (1081,)
            assert np.array_equal(got, expected)  # bit for bit: the same noise draws
            assert got.flags.writeable  # as the inline renderer's own array
            assert (got > 0.0).any()
    finally:
        worker.close()
        inline.close()


class _Broken(ScanRenderer):
    def render(self, name: str, t_s: float, truth: Pose2D) -> np.ndarray:
        raise ValueError(f"no site for {name} at {t_s}")


def test_a_failing_worker_raises_its_reason_here_and_closes() -> None:
    base = _renderer()
    broken = _Broken(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)})
    worker = WorkerScans(broken)
    try:
        worker.submit("left", 0.5, Pose2D(-14.0, 0.0, 0.0))
        with pytest.raises(RuntimeError, match=r"(?s)scan renderer failed.*no site for left"):
            worker.take()
        worker.submit("left", 0.6, Pose2D(-14.0, 0.0, 0.0))  # to a worker that has exited
        with pytest.raises(RuntimeError, match="exited without a scan"):
            worker.take()
    finally:
        worker.close()
    assert not worker._process.is_alive()


def test_open_scans_forks_only_when_asked() -> None:
    inline = open_scans(_renderer(), worker=False)
    assert isinstance(inline, InlineScans)
    worker = open_scans(_renderer(), worker=True)
    try:
        assert isinstance(worker, WorkerScans)
    finally:
        worker.close()


def test_a_short_approach_is_the_same_run_with_the_worker() -> None:
    config = load_config("flatbed")
    params = DockRunParams(seed=5, start_y_m=0.4, start_heading_deg=-2.0, timeout_s=3.0)
    inline = run_dock(config, params)
    worker = run_dock(config, dataclasses.replace(params, render_worker=True))
    assert inline.reason == "timeout"  # moving: 3 s of a 60 s approach
    assert dataclasses.replace(worker, wall_time_s=0.0) == dataclasses.replace(
        inline, wall_time_s=0.0
    )
    assert math.isfinite(inline.estimate_error_m) and inline.estimate_error_m < 0.05


def test_a_scan_later_than_the_localizer_takes_is_never_used() -> None:
    # Delivered after the localizer's staleness limit (0.12 s): no scan is ever used,
    # the vehicle never gets a pose and never moves.
    config = load_config("flatbed")
    result = run_dock(config, DockRunParams(seed=5, scan_latency_s=0.2, timeout_s=30.0))
    assert not result.success
    assert result.reason.startswith("localization lost"), result.reason
    assert result.final_speed_mps == 0.0
    assert result.gap_m == pytest.approx(10.0, abs=1e-9)
