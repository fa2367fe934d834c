"""The simulated receiver: what it writes parses back, through the daemon's own NMEA receiver,
to the pose it was given, and each fault it injects shows the way it was configured."""

from __future__ import annotations

import dataclasses
import math
import os
import re
import select
import statistics
import time
from collections import Counter
from typing import TypeVar

import pymap3d
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from appliance.sim.twins.gnss import (
    Dropout,
    GnssTwin,
    GnssTwinParams,
    NmeaEpoch,
    NmeaSynth,
    QualityChange,
)
from drivers.gnss import (
    FixQuality,
    GgaFix,
    GstError,
    Heading,
    NmeaEvent,
    NmeaReceiver,
    Reject,
    RmcFix,
    VtgVelocity,
)
from tests.unit.gnss.lines import xor_checksum

CLEAN = GnssTwinParams(position_noise_m=0.0, heading_noise_rad=0.0)
T = TypeVar("T")
LINE = re.compile(rb"\$(?P<body>[^*$]*)\*(?P<checksum>[0-9A-F]{2})\r\n")


def run(
    synth: NmeaSynth,
    seconds: float,
    pose: tuple[float, float, float, float] = (5.0, 7.0, 0.3, 4.0),
    step_s: float = 0.01,
) -> list[NmeaEpoch]:
    """Update as a simulator stepping at ``step_s`` would; the epochs that came out."""
    epochs = []
    for k in range(round(seconds / step_s)):
        epoch = synth.update(1000.0 + k * step_s, *pose)
        if epoch is not None:
            epochs.append(epoch)
    return epochs


def parse(epochs: list[NmeaEpoch]) -> tuple[list[NmeaEvent], NmeaReceiver]:
    receiver = NmeaReceiver()
    events: list[NmeaEvent] = []
    for epoch in epochs:
        for data in epoch.writes:
            receiver.receive_data(data)
            events += receiver.events()
    return events, receiver


def enu(
    params: GnssTwinParams,
    lat_deg: float | None,
    lon_deg: float | None,
    alt_m: float | None = None,
) -> tuple[float, float]:
    """East/north of a parsed fix, straight through pymap3d (not through the twin's frame).

    ``alt_m``: the fix's height, as the daemon takes it from the GGA (`gnss_pose`); the
    origin's when not given, which is a few hundred metres' approximation only: the twin's
    antenna rides the local tangent plane, 1.4 m above the origin's height 4.2 km out, and
    that height, dropped, moves the fix ~1 mm sideways (hypothesis found 1.009 mm)."""
    assert lat_deg is not None and lon_deg is not None
    height = params.origin_alt_m if alt_m is None else alt_m
    east, north, _ = pymap3d.geodetic2enu(
        lat_deg, lon_deg, height, params.origin_lat_deg, params.origin_lon_deg,
        params.origin_alt_m,
    )  # fmt: skip
    return float(east), float(north)


def of_type(events: list[NmeaEvent], kind: type[T]) -> list[T]:
    return [e for e in events if isinstance(e, kind)]


def test_the_origin_is_written_as_degrees_and_minutes() -> None:
    # 42.4591° N = 42° 27.546'; 71.2674° W = 71° 16.044' (worked out by hand).
    [epoch] = run(NmeaSynth(CLEAN), 0.01, pose=(0.0, 0.0, 0.0, 0.0))
    gga = epoch.writes[0].decode()
    assert gga.startswith("$GNGGA,120000.00,4227.5460000,N,07116.0440000,W,4,16,0.7,100.00,M,")
    assert [w[:6] for w in epoch.writes] == [b"$GNGGA", b"$GNRMC", b"$GNVTG", b"$GNHDT", b"$GNGST"]


@settings(max_examples=60, deadline=None)
# The corner of the area, where the tangent plane stands 1.4 m above the origin's height.
@example(0.0, 0.0, 3000.0, 2996.0, 0.0, 1.0, "GN")
@example(0.0, 0.0, -3000.0, -3000.0, 0.0, 1.0, "GP")
@given(
    origin_lat=st.floats(-80.0, 80.0),
    origin_lon=st.floats(-179.0, 179.0),
    east_m=st.floats(-3000.0, 3000.0),
    north_m=st.floats(-3000.0, 3000.0),
    yaw_rad=st.floats(-10.0, 10.0),
    speed_mps=st.floats(-20.0, 40.0).filter(lambda v: abs(v) > 0.05),
    talker=st.sampled_from(["GN", "GP"]),
)
def test_lines_parse_back_to_the_pose(
    origin_lat: float,
    origin_lon: float,
    east_m: float,
    north_m: float,
    yaw_rad: float,
    speed_mps: float,
    talker: str,
) -> None:
    params = dataclasses.replace(
        CLEAN, origin_lat_deg=origin_lat, origin_lon_deg=origin_lon, talker=talker,
        sentences=("GGA", "RMC", "VTG", "HDT", "THS", "GST"),
    )  # fmt: skip
    [epoch] = run(NmeaSynth(params), 0.01, pose=(east_m, north_m, yaw_rad, speed_mps))
    events, receiver = parse([epoch])
    assert receiver.counts == {}
    [gga], [rmc], [vtg] = (
        of_type(events, GgaFix),
        of_type(events, RmcFix),
        of_type(events, VtgVelocity),
    )
    [gst], headings = of_type(events, GstError), of_type(events, Heading)
    assert {e.talker for e in events} == {talker}
    for fix in (gga, rmc):  # to a millimetre, both hemispheres (the RMC has no height)
        east, north = enu(params, fix.lat_deg, fix.lon_deg, gga.altitude_m)
        assert math.hypot(east - east_m, north - north_m) < 1e-3
    # Heading: clockwise from north, from yaw counter-clockwise from east.
    expected_heading_deg = (90.0 - math.degrees(yaw_rad)) % 360.0
    for heading in headings:
        assert heading.valid and heading.heading_rad is not None
        difference = (math.degrees(heading.heading_rad) - expected_heading_deg + 180) % 360 - 180
        assert abs(difference) < 1e-3
    expected_course_deg = (expected_heading_deg + (180.0 if speed_mps < 0 else 0.0)) % 360.0
    for course_rad in (rmc.course_rad, vtg.course_rad):
        assert course_rad is not None
        difference = (math.degrees(course_rad) - expected_course_deg + 180) % 360 - 180
        assert abs(difference) < 0.006
    assert rmc.speed_mps == pytest.approx(abs(speed_mps), abs=0.001)
    assert vtg.speed_mps == pytest.approx(abs(speed_mps), abs=0.001)
    assert rmc.valid and vtg.valid and gga.quality is FixQuality.RTK_FIXED
    assert gst.sigma_lat_m == gst.sigma_lon_m == 0.0


@settings(max_examples=60, deadline=None)
@given(
    origin_lat=st.floats(-89.9, 89.9),
    origin_lon=st.floats(-180.0, 180.0),
    origin_alt=st.floats(-430.0, 8850.0),
    hdop=st.floats(0.0, 99.9),
    quality=st.sampled_from(list(FixQuality)),
    speed_mps=st.floats(-100.0, 100.0),
    decimals=st.integers(4, 8),
)
def test_every_line_is_framed_checksummed_and_within_82_characters(
    origin_lat: float,
    origin_lon: float,
    origin_alt: float,
    hdop: float,
    quality: FixQuality,
    speed_mps: float,
    decimals: int,
) -> None:
    params = GnssTwinParams(
        origin_lat_deg=origin_lat, origin_lon_deg=origin_lon, origin_alt_m=origin_alt,
        hdop=hdop, quality=quality, minute_decimals=decimals, position_noise_m=3.0,
        sentences=("GGA", "RMC", "VTG", "HDT", "THS", "GST"),
    )  # fmt: skip
    [epoch] = run(NmeaSynth(params), 0.01, pose=(50.0, -20.0, 1.0, speed_mps))
    for line in epoch.writes:
        match = LINE.fullmatch(line)
        assert match is not None, line
        assert len(line) <= 82, line
        assert int(match["checksum"], 16) == xor_checksum(match["body"].decode())
    events, receiver = parse([epoch])
    assert receiver.counts == {}
    assert len(events) == 6


def test_epochs_come_at_the_configured_rate_on_the_utc_grid() -> None:
    for rate_hz in (1.0, 10.0, 20.0):
        synth = NmeaSynth(dataclasses.replace(CLEAN, rate_hz=rate_hz))
        epochs = run(synth, 3.0, step_s=0.005)
        assert len(epochs) == round(3.0 * rate_hz)
        events, _ = parse(epochs)
        times = [e.utc_time_of_day_s for e in of_type(events, GgaFix)]
        assert times == pytest.approx([12 * 3600 + k / rate_hz for k in range(len(times))])


def test_a_late_caller_gets_one_epoch_not_a_burst() -> None:
    synth = NmeaSynth(CLEAN)
    assert synth.update(0.0, 0.0, 0.0, 0.0, 0.0) is not None
    assert synth.update(0.05, 0.0, 0.0, 0.0, 0.0) is None
    late = synth.update(0.95, 0.0, 0.0, 0.0, 0.0)
    assert late is not None and late.t_s == pytest.approx(0.9)
    assert synth.update(0.99, 0.0, 0.0, 0.0, 0.0) is None
    assert synth.epochs == 2


def test_the_jumps_switch_a_03_m_offset_every_period() -> None:
    params = dataclasses.replace(CLEAN, jump_m=0.3, jump_period_s=2.0)
    truth = (5.0, 7.0)
    events, _ = parse(run(NmeaSynth(params, seed=3), 10.0, pose=(*truth, 0.3, 4.0)))
    directions: dict[int, float] = {}
    for gga in of_type(events, GgaFix):
        assert gga.utc_time_of_day_s is not None
        t_s = gga.utc_time_of_day_s - 12 * 3600
        east, north = enu(params, gga.lat_deg, gga.lon_deg)
        offset = (east - truth[0], north - truth[1])
        period = math.floor(t_s / 2.0 + 1e-6)
        if period % 2 == 0:  # 0-2 s, 4-6 s, 8-10 s: the GPS solution, no offset
            assert math.hypot(*offset) < 1e-3, t_s
        else:  # 2-4 s and 6-8 s: the other solution, 0.3 m away, one direction per period
            assert math.hypot(*offset) == pytest.approx(0.3, abs=1e-3), t_s
            direction = math.atan2(offset[1], offset[0])
            assert directions.setdefault(period, direction) == pytest.approx(direction, abs=0.01)
    assert sorted(directions) == [1, 3]
    assert abs(math.remainder(directions[1] - directions[3], math.tau)) > 0.01  # drawn anew


def test_scheduled_dropouts_send_nothing() -> None:
    params = dataclasses.replace(CLEAN, dropouts=(Dropout(1.0, 0.5), Dropout(2.5, 0.2)))
    epochs = run(NmeaSynth(params), 4.0)
    silent = [round(e.t_s, 3) for e in epochs if not e.writes]
    assert silent == [1.0, 1.1, 1.2, 1.3, 1.4, 2.5, 2.6]
    assert all(e.dropout == (not e.writes) for e in epochs)
    events, _ = parse(epochs)
    times = [e.utc_time_of_day_s - 12 * 3600 for e in of_type(events, GgaFix)]  # type: ignore[operator]
    assert not any(1.0 - 1e-6 <= t < 1.5 - 1e-6 or 2.5 - 1e-6 <= t < 2.7 - 1e-6 for t in times)
    assert len(times) == 40 - 7


def test_random_dropouts_are_seeded_and_about_as_often_as_configured() -> None:
    params = dataclasses.replace(CLEAN, random_dropouts_per_s=0.2, random_dropout_s=1.0)

    def silent(seed: int) -> list[float]:
        synth = NmeaSynth(params, seed=seed)
        return [k / 10 for k in range(6000) if synth.in_dropout(k / 10)]

    first = silent(5)
    assert first == silent(5)
    assert first != silent(6)
    # A renewal process: on average 5 s up, then 1 s down, so about 1/6 of the time silent.
    assert 0.11 < len(first) / 6000 < 0.22
    # Silences come as whole seconds: a run of silent epochs lasts 10 of them (1.0 s).
    runs = Counter(round(t - k * 0.1, 3) for k, t in enumerate(first))
    assert all(n % 10 == 0 for n in runs.values())
    # And the synth sends nothing in them.
    epochs = run(NmeaSynth(params, seed=5), 30.0, step_s=0.1)
    assert [round(e.t_s, 3) for e in epochs if not e.writes] == [t for t in first if t < 30.0]


def test_quality_changes_show_in_gga_gst_and_rmc() -> None:
    params = dataclasses.replace(
        CLEAN,
        quality_changes=(
            QualityChange(1.0, FixQuality.GPS, 0.0, 9, 1.4),
            QualityChange(2.0, FixQuality.INVALID, 0.0, 3, 9.9),
            QualityChange(3.0, FixQuality.RTK_FLOAT, 0.0, 12, 0.9),
        ),
    )
    events, receiver = parse(run(NmeaSynth(params), 4.0))
    assert receiver.counts == {}
    ggas = of_type(events, GgaFix)
    assert [g.quality for g in ggas[::10]] == [
        FixQuality.RTK_FIXED, FixQuality.GPS, FixQuality.INVALID, FixQuality.RTK_FLOAT,
    ]  # fmt: skip
    assert [g.satellites for g in ggas[::10]] == [16, 9, 3, 12]
    no_fix = slice(20, 30)
    assert all(g.lat_deg is None and g.lon_deg is None for g in ggas[no_fix])
    assert all(g.differential_age_s is None for g in ggas[10:30])  # GPS, no fix: no corrections
    assert [r.valid for r in of_type(events, RmcFix)[::10]] == [True, True, False, True]
    assert [h.valid for h in of_type(events, Heading)[::10]] == [True, True, False, True]
    assert [g.sigma_lat_m for g in of_type(events, GstError)[::10]] == [0.0, 0.0, None, 0.0]


def test_noise_has_the_configured_sigma_and_gst_reports_it() -> None:
    params = dataclasses.replace(
        CLEAN,
        position_noise_m=0.05,
        heading_noise_rad=math.radians(0.5),
        quality_changes=(QualityChange(30.0, FixQuality.GPS, 1.5, 8, 1.2),),
    )
    truth = (5.0, 7.0, 0.3, 4.0)
    events, _ = parse(run(NmeaSynth(params, seed=11), 60.0, pose=truth, step_s=0.1))
    ggas, gsts = of_type(events, GgaFix), of_type(events, GstError)
    for phase, sigma in ((slice(0, 300), 0.05), (slice(300, 600), 1.5)):
        errors = [enu(params, g.lat_deg, g.lon_deg) for g in ggas[phase]]
        east = [e - truth[0] for e, _ in errors]
        north = [n - truth[1] for _, n in errors]
        for axis in (east, north):  # 300 samples: the sample sigma is within ~4 % (1 sd)
            assert statistics.stdev(axis) == pytest.approx(sigma, rel=0.2)
            assert abs(statistics.fmean(axis)) < 4 * sigma / math.sqrt(300)
        assert {g.sigma_lat_m for g in gsts[phase]} == {sigma}
    expected_heading_deg = 90.0 - math.degrees(0.3)
    headings_rad = [h.heading_rad for h in of_type(events, Heading)]
    heading_errors = [math.degrees(h) - expected_heading_deg for h in headings_rad if h is not None]
    assert len(heading_errors) == 600
    assert statistics.stdev(heading_errors) == pytest.approx(0.5, rel=0.2)


def test_corrupted_lines_are_exactly_the_checksum_rejects() -> None:
    params = dataclasses.replace(
        CLEAN, corrupt_fraction=0.2, split_fraction=0.3, merge_fraction=0.3
    )
    synth = NmeaSynth(params, seed=2)
    epochs = run(synth, 30.0, step_s=0.1)
    events, receiver = parse(epochs)
    assert synth.lines == 1500
    assert synth.corrupted_lines == sum(e.corrupted for e in epochs)
    # Binomial(1500, 0.2): 300 expected, sd 15.5.
    assert 250 < synth.corrupted_lines < 350
    assert receiver.counts == {Reject.CHECKSUM: synth.corrupted_lines}
    assert len(events) == synth.lines - synth.corrupted_lines


def test_split_and_merged_writes_carry_the_same_bytes_and_reassemble() -> None:
    whole = run(NmeaSynth(CLEAN, seed=4), 5.0)
    split_params = dataclasses.replace(CLEAN, split_fraction=0.5, merge_fraction=0.4)
    split = run(NmeaSynth(split_params, seed=4), 5.0)
    assert [b"".join(e.writes) for e in split] == [b"".join(e.writes) for e in whole]
    writes = [w for e in split for w in e.writes]
    assert any(not w.endswith(b"\r\n") for w in writes)  # a line cut across two writes
    assert any(w.count(b"\r\n") >= 2 for w in writes)  # several lines in one write
    assert all(len(e.writes) == e.lines for e in whole)  # without them: one line, one write
    assert parse(split)[0] == parse(whole)[0]


def test_the_seed_makes_it_reproducible() -> None:
    noisy = dataclasses.replace(
        GnssTwinParams(), jump_m=0.3, jump_period_s=1.0, corrupt_fraction=0.1
    )
    first = [e.writes for e in run(NmeaSynth(noisy, seed=9), 3.0)]
    assert first == [e.writes for e in run(NmeaSynth(noisy, seed=9), 3.0)]
    assert first != [e.writes for e in run(NmeaSynth(noisy, seed=10), 3.0)]
    synth = NmeaSynth(noisy, seed=9)
    run(synth, 1.0)
    synth.reset()
    assert [e.writes for e in run(synth, 3.0)] == first


@pytest.mark.parametrize(
    ("change", "complaint"),
    [
        ({"rate_hz": 25.0}, "rate_hz"),
        ({"rate_hz": 0.5}, "rate_hz"),
        ({"talker": "gn"}, "talker"),
        ({"talker": "GNS"}, "talker"),
        ({"sentences": ("GGA", "GSV")}, "sentences"),
        ({"sentences": ()}, "sentences"),
        ({"sentences": ("GGA", "GGA")}, "sentences"),
        ({"corrupt_fraction": 1.5}, "corrupt_fraction"),
        ({"position_noise_m": -0.1}, "position_noise_m"),
        ({"jump_period_s": 0.0}, "jump_period_s"),
        ({"origin_lat_deg": 91.0}, "latitude"),
        ({"minute_decimals": 9}, "minute_decimals"),
        ({"quality_changes": (QualityChange(2.0, FixQuality.GPS, 1.0, 8, 1.0),
                              QualityChange(1.0, FixQuality.GPS, 1.0, 8, 1.0))}, "time order"),
    ],
)  # fmt: skip
def test_bad_parameters_are_refused(change: dict[str, object], complaint: str) -> None:
    with pytest.raises(ValueError, match=complaint):
        dataclasses.replace(GnssTwinParams(), **change)  # type: ignore[arg-type]


def test_the_twin_writes_to_a_pty_and_unplugs_like_a_cable(tmp_path: object) -> None:
    path = os.path.join(str(tmp_path), "gnss")
    twin = GnssTwin(path, CLEAN)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        for k in range(3):
            twin.update(k * 0.1, 1.0, 2.0, 0.0, 1.0)
        receiver, events = NmeaReceiver(), list[NmeaEvent]()
        deadline_s = time.monotonic() + 2.0
        while len(events) < 15 and time.monotonic() < deadline_s:
            # A pty hands written bytes over asynchronously: wait for them.
            if select.select([fd], [], [], 0.05)[0]:
                receiver.receive_data(os.read(fd, 4096))
                events += receiver.events()
        assert len(events) == 15 and receiver.counts == {}
        twin.unplug()
        assert not os.path.exists(path)
        assert os.read(fd, 100) == b""  # EOF: the line hung up
        assert twin.update(0.3, 1.0, 2.0, 0.0, 1.0) is not None  # the receiver goes on alone
        os.close(fd)
        twin.replug()
        assert os.path.islink(path)
    finally:
        twin.close()
