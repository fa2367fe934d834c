"""Device time unwrapping: a wrap is continued, a reboot starts a new epoch."""

from __future__ import annotations

import pytest

from drivers.lms111 import DeviceTimeUnwrapper, ProtocolError, UnwrapParams
from drivers.lms111.timebase import WRAP_US

SCAN_PERIOD_US = 20_000  # 50 Hz


def test_steady_counter_passes_through() -> None:
    unwrap = DeviceTimeUnwrapper()
    assert [unwrap.update(t) for t in (1_000, 21_000, 41_000)] == [1_000, 21_000, 41_000]
    assert (unwrap.wraps, unwrap.reboots, unwrap.epoch) == (0, 0, 0)


def test_unwraps_across_the_32_bit_wrap() -> None:
    unwrap = DeviceTimeUnwrapper()
    start = WRAP_US - 3 * SCAN_PERIOD_US + 123
    raws = [(start + i * SCAN_PERIOD_US) % WRAP_US for i in range(6)]
    unwrapped = [unwrap.update(raw) for raw in raws]
    assert unwrapped == [start + i * SCAN_PERIOD_US for i in range(6)]
    assert raws[3] < raws[2]  # the raw counter really wrapped
    assert (unwrap.wraps, unwrap.reboots) == (1, 0)


def test_twice_around_the_clock() -> None:
    unwrap = DeviceTimeUnwrapper()
    step = 1_000_000_000  # 1000 s between samples, never more than max_gap across the wrap
    unwrap = DeviceTimeUnwrapper(UnwrapParams(max_gap_us=step))
    values = [unwrap.update((i * step) % WRAP_US) for i in range(10)]
    assert values == [i * step for i in range(10)]
    assert unwrap.wraps == 2


def test_reboot_is_not_taken_for_a_wrap() -> None:
    unwrap = DeviceTimeUnwrapper()
    unwrap.update(1_800_000_000)  # 30 min after power-up
    unwrap.update(1_800_020_000)
    after_reboot = unwrap.update(25_000_000)  # scanner came back 25 s after power-up
    assert after_reboot == 25_000_000
    assert (unwrap.wraps, unwrap.reboots, unwrap.epoch) == (0, 1, 1)
    assert unwrap.update(25_020_000) == 25_020_000


def test_reboot_just_before_the_wrap_is_told_apart_by_host_time() -> None:
    """Near the wrap the raw values alone are ambiguous; elapsed host time decides."""
    near_top = WRAP_US - 5_000_000
    by_value = DeviceTimeUnwrapper()
    by_value.update(near_top)
    by_value.update(20_000_000)  # 25 s "later" on a modular clock: looks like a wrap
    assert by_value.wraps == 1

    by_host_time = DeviceTimeUnwrapper()
    by_host_time.update(near_top, now_s=100.0)
    assert by_host_time.update(20_000_000, now_s=102.0) == 20_000_000  # only 2 s passed
    assert (by_host_time.wraps, by_host_time.reboots) == (0, 1)

    real_wrap = DeviceTimeUnwrapper()
    real_wrap.update(near_top, now_s=100.0)
    assert real_wrap.update(20_000_000, now_s=125.0) == WRAP_US + 20_000_000
    assert real_wrap.wraps == 1


def test_reset_and_bad_input() -> None:
    unwrap = DeviceTimeUnwrapper()
    unwrap.update(WRAP_US - 1)
    unwrap.update(5)
    unwrap.reset()
    assert unwrap.update(7) == 7
    assert unwrap.wraps == 0
    with pytest.raises(ProtocolError):
        unwrap.update(WRAP_US)
    with pytest.raises(ProtocolError):
        unwrap.update(-1)
