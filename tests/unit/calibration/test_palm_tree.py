"""The palm tree on the simulated vehicle: the wheel to tyre map within 0.3 deg."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.palm_tree import (
    FIX_SIGMA,
    HEADING_JUMP,
    POSITION_JUMP,
    STOPPED,
    TIME_GAP,
    PalmTreeParams,
    fit_palm_tree,
)
from calibration.palm_tree_samples import PalmTreeRecorder, PalmTreeSamples
from tests.unit.calibration.vehicle_runs import (
    ANTENNA_FORWARD_M,
    HALF_TURNS_RAD,
    TRUE_K,
    V_CHAR_MPS,
    WHEELBASE_M,
    GnssErrors,
    Recorder,
    palm_tree,
    true_tyre_rad,
)

PARAMS = PalmTreeParams(
    wheelbase_m=WHEELBASE_M,
    antenna_forward_m=ANTENNA_FORWARD_M,
    characteristic_speed_mps=V_CHAR_MPS,
)
FULL_LOCK_RAD = HALF_TURNS_RAD[-1]


@pytest.fixture(scope="module", params=[1, 2, 3])
def recording(request: pytest.FixtureRequest) -> Recorder:
    """Walking pace (1 m/s), up to half a circle or 12 m, 2 cm fixes, 0.3 m jumps."""
    return palm_tree(seed=request.param)


def test_the_map_is_within_0_3_deg_of_the_linkage_from_lock_to_lock(recording: Recorder) -> None:
    fit = fit_palm_tree(recording.samples(), PARAMS)
    assert fit.accepted, fit.reasons
    assert fit.tyre_map is not None
    tyre_map = fit.tyre_map.tyre_map
    assert tyre_map.wheel_min_rad < -FULL_LOCK_RAD + 0.05
    assert tyre_map.wheel_max_rad > FULL_LOCK_RAD - 0.05
    wheel = np.linspace(tyre_map.wheel_min_rad, tyre_map.wheel_max_rad, 400)
    error_deg = np.degrees(np.abs(tyre_map.tyre_rad(wheel) - true_tyre_rad(wheel)))
    assert float(np.max(error_deg)) < 0.3
    assert fit.tyre_map.monotonic
    assert fit.tyre_map.residual_max_deg < PARAMS.max_map_residual_deg


def test_arcs_at_too_few_wheel_magnitudes_are_refused_not_fitted() -> None:
    """Five arcs, but at 0, ±π and ±2.3π: an odd map of three powers has only two
    magnitudes to go by, and would swing freely between them."""
    wheels = (-2.3 * math.pi, -math.pi, 0.0, math.pi, 2.3 * math.pi)
    fit = fit_palm_tree(palm_tree(wheels_rad=wheels).samples(), PARAMS)
    assert len(fit.arcs) >= 5  # forward and back at each (straight ahead: no circle)
    assert not fit.accepted and fit.tyre_map is None
    assert any("pin 2 of the map's 3 coefficients" in r for r in fit.reasons), fit.reasons


def test_each_arc_gives_both_tyre_angles_within_its_sigmas(recording: Recorder) -> None:
    fit = fit_palm_tree(recording.samples(), PARAMS)
    front_miss, rear_miss = [], []
    for arc in fit.arcs:
        front = float(true_tyre_rad(arc.wheel_rad))
        front_miss.append((arc.front_rad - front) / arc.front_sigma_rad)
        rear_miss.append((arc.rear_rad - TRUE_K * front) / arc.rear_sigma_rad)
        assert abs(arc.front_rad - front) < math.radians(0.3)
        assert abs(arc.rear_rad - TRUE_K * front) < math.radians(0.5)
        assert arc.residual_rms_m < 2 * arc.fix_sigma_m
    # Sigmas a fair size: misses beyond four of them would be a biased method.
    assert max(abs(m) for m in front_miss + rear_miss) < 4.0


def test_every_jump_is_a_break_and_nothing_else_is(recording: Recorder) -> None:
    samples = recording.samples()
    fit = fit_palm_tree(samples, PARAMS)
    switches = math.floor(samples.t_s[-1] / GnssErrors().jump_period_s)
    assert fit.breaks == {POSITION_JUMP: switches}


def test_no_jumps_no_breaks() -> None:
    fit = fit_palm_tree(palm_tree(GnssErrors(jump_m=0.0), seed=4).samples(), PARAMS)
    assert fit.breaks == {}
    assert len(fit.arcs) == len(HALF_TURNS_RAD)  # one arc per held wheel angle
    assert fit.rejected == {}


def test_without_v_char_the_turns_read_small_by_the_sideslip_gain(recording: Recorder) -> None:
    samples = recording.samples()
    with_gain = fit_palm_tree(samples, PARAMS)
    without = fit_palm_tree(samples, PalmTreeParams(WHEELBASE_M, ANTENNA_FORWARD_M))
    for arc, plain in zip(with_gain.arcs, without.arcs, strict=True):
        assert plain.sideslip_gain == 1.0
        # tan φf + tan φr scales with G_ss; tan φf - tan φr does not.
        sum_tan = math.tan(arc.front_rad) + math.tan(arc.rear_rad)
        plain_sum = math.tan(plain.front_rad) + math.tan(plain.rear_rad)
        assert plain_sum == pytest.approx(sum_tan * arc.sideslip_gain, rel=1e-9, abs=1e-12)


def test_rejection_counts_add_up(recording: Recorder) -> None:
    samples = recording.samples()
    fit = fit_palm_tree(samples, PARAMS)
    assert fit.samples_used + sum(fit.rejected_samples.values()) == len(samples)
    assert fit.samples_used == sum(arc.samples for arc in fit.arcs)


def test_a_heading_step_and_a_dropout_are_breaks() -> None:
    s = palm_tree(GnssErrors(jump_m=0.0), seed=5).samples()
    heading = s.heading_rad.copy()
    heading[300:] += math.radians(3.0)
    keep = np.ones(len(s), bool)
    keep[600:610] = False  # a second without epochs
    columns = [getattr(s, name)[keep] for name in PalmTreeSamples.__dataclass_fields__]
    columns[3] = heading[keep]
    fit = fit_palm_tree(PalmTreeSamples(*columns), PARAMS)
    assert fit.breaks == {HEADING_JUMP: 1, TIME_GAP: 1}


def synthetic(pieces: list[tuple[float, int, float, bool]], jumps: list[int]) -> PalmTreeSamples:
    """Pieces of (wheel, epochs, speed, poor fix) driven at 10 Hz on a 1:18 map."""
    rows, x, y, heading, t = [], 0.0, 0.0, 0.0, 0.0
    for wheel, epochs, speed, poor in pieces:
        kappa = 2 * math.tan(wheel / 18.0) / WHEELBASE_M
        for _ in range(epochs):
            t += 0.1
            heading += kappa * speed * 0.1
            x += speed * 0.1 * math.cos(heading)
            y += speed * 0.1 * math.sin(heading)
            rows.append([t, x, y, heading, speed, wheel, 0.2 if poor else 0.01])
    table = np.array(rows)
    for at in jumps:
        table[at % len(table) :, 1] += 0.3
    return PalmTreeSamples(*table.T)


@settings(max_examples=40)
@given(
    st.lists(
        st.tuples(
            st.sampled_from([-9.0, -4.5, 0.0, 3.0, 9.0]),
            st.integers(1, 60),
            st.sampled_from([0.0, 0.1, 1.0, 1.5]),
            st.booleans(),
        ),
        min_size=1,
        max_size=8,
    ),
    st.lists(st.integers(0, 10_000), max_size=3),
)
def test_every_sample_and_arc_is_counted_once(
    pieces: list[tuple[float, int, float, bool]], jumps: list[int]
) -> None:
    samples = synthetic(pieces, jumps)
    fit = fit_palm_tree(samples, PalmTreeParams(WHEELBASE_M))
    good = samples.fix_sigma_m <= PARAMS.max_fix_sigma_m
    moving = np.abs(samples.speed_mps) >= PARAMS.min_speed_mps
    assert fit.rejected_samples.get(FIX_SIGMA, 0) == int(np.sum(~good))
    assert fit.rejected_samples.get(STOPPED, 0) == int(np.sum(good & ~moving))
    arc_rejections = sum(
        n for r, n in fit.rejected_samples.items() if r not in (FIX_SIGMA, STOPPED)
    )
    assert fit.samples_used + arc_rejections == int(np.sum(good & moving))
    assert all(n > 0 for n in fit.rejected.values())
    assert set(fit.rejected) == set(fit.rejected_samples) - {FIX_SIGMA, STOPPED}
    assert fit.accepted == (not fit.reasons)


def test_the_recorder_shows_metres_per_half_turn_and_gives_the_samples() -> None:
    source = palm_tree(GnssErrors(jump_m=0.0), seed=6).samples()
    recorder = PalmTreeRecorder()
    recorder.update(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01)
    recorder.reset()
    for row in zip(
        *(getattr(source, n) for n in PalmTreeSamples.__dataclass_fields__), strict=True
    ):
        recorder.update(*(float(v) for v in row))
    coverage = recorder.coverage_m()
    assert list(coverage) == pytest.approx(list(HALF_TURNS_RAD))
    assert all(metres > 10.0 for metres in coverage.values())  # forward and back again
    assert np.array_equal(recorder.samples().x_m, source.x_m)
    with pytest.raises(ValueError, match="not after"):
        recorder.update(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01)
    with pytest.raises(ValueError, match="non-finite"):
        recorder.update(1e9, math.nan, 0.0, 0.0, 0.0, 0.0, 0.01)


def column_set(n: int = 30, **changes: object) -> dict[str, object]:
    columns: dict[str, object] = {
        name: np.linspace(0.0, 1.0, n) for name in PalmTreeSamples.__dataclass_fields__
    }
    columns["t_s"] = np.arange(n) * 0.1
    columns.update(changes)
    return columns


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"x_m": np.full(30, math.nan)}, "x_m holds 30 non-finite"),
        ({"y_m": np.zeros(29)}, "differ in length"),
        ({"t_s": np.zeros(30)}, "t_s must increase"),
        ({"fix_sigma_m": -np.ones(30)}, "negative"),
        ({"wheel_rad": np.zeros((30, 2))}, "one-dimensional"),
    ],
)
def test_garbage_raises_value_error(changes: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PalmTreeSamples(**column_set(**changes))  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"wheelbase_m": 0.0}, "wheelbase_m must be a positive"),
        ({"characteristic_speed_mps": -1.0}, "characteristic_speed_mps"),
        ({"jump_window": 4}, "jump_window"),
    ],
)
def test_bad_parameters_raise_value_error(changes: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        PalmTreeParams(**{"wheelbase_m": 3.6, **changes})  # type: ignore[arg-type]


@st.composite
def columns_maybe_spoilt(draw: st.DrawFn) -> dict[str, object]:
    """Seven columns of one length, time increasing, then perhaps one thing spoilt."""
    n = draw(st.integers(1, 80))
    values = st.lists(st.floats(-1e4, 1e4), min_size=n, max_size=n)
    names = list(PalmTreeSamples.__dataclass_fields__)
    columns: dict[str, object] = {name: np.array(draw(values)) for name in names}
    steps = draw(st.lists(st.floats(1e-3, 2.0), min_size=n, max_size=n))
    columns["t_s"] = np.cumsum(steps)
    columns["fix_sigma_m"] = np.abs(np.asarray(columns["fix_sigma_m"])) * 1e-5
    name = draw(st.sampled_from(names))
    spoil = draw(st.sampled_from(["none", "nan", "inf", "short", "2-d", "text"]))
    column = np.asarray(columns[name], dtype=float)
    if spoil in ("nan", "inf"):
        column[draw(st.integers(0, n - 1))] = math.nan if spoil == "nan" else math.inf
        columns[name] = column
    elif spoil == "short":
        columns[name] = column[:-1]
    elif spoil == "2-d":
        columns[name] = column.reshape(1, -1)
    elif spoil == "text":
        columns[name] = ["x"] * n
    return columns


@settings(max_examples=80)
@given(columns_maybe_spoilt())
def test_any_columns_fit_or_raise_value_error(columns: dict[str, object]) -> None:
    """Garbage in gives ValueError, never another exception; what passes the checks fits."""
    try:
        samples = PalmTreeSamples(**columns)  # type: ignore[arg-type]
    except ValueError:
        return
    fit = fit_palm_tree(samples, PARAMS)
    assert fit.samples_used + sum(fit.rejected_samples.values()) == len(samples)
