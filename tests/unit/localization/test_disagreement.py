"""The localizer's verdict that a landmark disagrees with the map (its sightings over the
last `disagreement_window_s`): persistently large innovations or mostly kept out say the
map is not the launcher; one outlier among many good sightings says nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from appliance.localization.launcher_localizer import (
    LauncherLocalizer,
    LocalizerParams,
    ScannerSetup,
    _Verdicts,
)
from tests.unit.localization.test_launcher_localizer import MOUNTS

PERIOD_S = 0.02  # a sighting per scan at 50 Hz
GATE = float(chi2.ppf(0.999, 2))


def verdicts(sightings: list[tuple[bool, float]]) -> list[str]:
    """What the localizer says of cylinder_left after these sightings, one per scan."""
    localizer = LauncherLocalizer({n: ScannerSetup(m) for n, m in MOUNTS.items()})
    # the 99.9 % gate the mean is capped at (closed form there, scipy here: to rounding)
    assert localizer.ekf.gate_2d == pytest.approx(GATE, rel=1e-14)
    window = localizer.params.disagreement_window_s
    record = localizer._verdicts.setdefault("cylinder_left", _Verdicts())
    for k, (accepted, nis) in enumerate(sightings):
        record.add(k * PERIOD_S, accepted, nis, window, localizer.ekf.gate_2d)
    return localizer._disagreeing_landmarks()


def good(n: int, seed: int = 0) -> list[tuple[bool, float]]:
    """Sightings of a landmark where the map puts it: NIS ~ chi2(2), accepted."""
    rng = np.random.default_rng(seed)
    return [(True, float(v)) for v in rng.chisquare(2, n)]


def test_good_sightings_agree() -> None:
    assert verdicts(good(200)) == []


def test_one_wild_outlier_among_many_good_sightings_says_nothing() -> None:
    # Before the cap: one sighting at NIS 500 in a window of 100 made the mean ~7 > 6.
    sightings = [*good(150), (False, 500.0), *good(10, seed=1)]
    assert verdicts(sightings) == []


def test_persistently_large_innovations_disagree() -> None:
    # A cylinder a little off its place: accepted, but NIS about 8 every time.
    rng = np.random.default_rng(2)
    biased = [(True, float(v)) for v in rng.noncentral_chisquare(2, 6.0, 200)]
    assert verdicts(biased) == ["cylinder_left disagrees with the map"]


def test_mostly_kept_out_or_missing_is_said_as_such() -> None:
    kept_out = [(False, 80.0) if k % 3 else (True, 1.0) for k in range(200)]
    assert verdicts(kept_out) == ["cylinder_left disagrees with the map"]
    missing = [(False, math.nan) if k % 3 else (True, 1.0) for k in range(200)]
    assert verdicts(missing) == ["cylinder_left not seen where the map puts it"]


def test_params_are_the_defaults_the_figures_above_assume() -> None:
    p = LocalizerParams()
    assert (p.disagreement_window_s, p.disagreement_mean_nis) == (2.0, 6.0)
    assert p.disagreement_fraction == 0.5 and p.disagreement_min_sightings == 10
