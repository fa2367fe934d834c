"""LMS111 scan decode cost: a 1,081-point DIST1 + RSSI1 scan, CoLa-A and CoLa-B.

Targets (issue: the sans-I/O LMS111 core): median <= 0.3 ms in CoLa-A and <= 0.1 ms in
CoLa-B on the project machine. "decode" is `parse_telegram` on an already framed telegram
plus the SI views (`ranges_m`, `angles_rad`, `intensities`) a consumer reads; "framing
included" adds `receive_data` + `next_event` on the raw bytes, as the asyncio client does.
Two scanners at 50 Hz give 100 scans/s, so 0.3 ms is 3 % of one core.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from benchmarks.stats import summarize
from drivers.lms111 import (
    Dialect,
    Lms111Connection,
    Scan,
    ScanTelegram,
    Telegram,
    encode_scan_telegram,
    parse_telegram,
    scan_from_ranges,
)

POINTS = 1081
WARMUP = 200
SAMPLES = 3000


def realistic_scan() -> Scan:
    """Ranges 0.5-20 m with a few dropouts, RSSI 0-255, -45..225 deg at 0.25 deg."""
    rng = np.random.default_rng(7)
    ranges_m = rng.uniform(0.5, 20.0, POINTS)
    ranges_m[rng.random(POINTS) < 0.05] = 0.0
    intensities = rng.integers(0, 256, POINTS)
    scan = scan_from_ranges(ranges_m, angular_step_deg=0.25, intensities=intensities)
    return replace(
        scan,
        serial_number=0x0123ABCD,
        telegram_counter=0xBEEF,
        scan_counter=0xBEF0,
        device_time_us=0xA1B2C3D4,
        transmit_time_us=0xA1B2F000,
        measurement_frequency_100hz=0x2D0,
    )


def _time_ms(operation: Callable[[], object]) -> list[float]:
    for _ in range(WARMUP):
        operation()
    samples = []
    for _ in range(SAMPLES):
        start = time.perf_counter_ns()
        operation()
        samples.append((time.perf_counter_ns() - start) / 1e6)
    return samples


def _consume(scan: Scan) -> None:
    """What a consumer touches: the SI arrays (computed lazily, so included here)."""
    _ = (scan.ranges_m, scan.angles_rad, scan.intensities)


def bench_dialect(dialect: Dialect, scan: Scan) -> list[str]:
    wire = encode_scan_telegram(scan, dialect)
    payload = wire[1:-1] if dialect is Dialect.COLA_A else wire[8:-1]
    telegram = Telegram(dialect, payload)

    def decode_only() -> None:
        event = parse_telegram(telegram)
        assert isinstance(event, ScanTelegram)
        _consume(event.scan)

    connection = Lms111Connection(dialect)

    def with_framing() -> None:
        connection.receive_data(wire)
        event = connection.next_event(host_receive_time_s=0.0)
        assert isinstance(event, ScanTelegram)
        _consume(event.scan)

    label = f"decode {dialect.value} {POINTS} pts + RSSI ({len(wire)} B)"
    return [
        summarize(label, _time_ms(decode_only), "ms"),
        summarize(label + ", framing included", _time_ms(with_framing), "ms"),
        summarize(
            f"encode {dialect.value} {POINTS} pts + RSSI, framed (the twin's cost)",
            _time_ms(lambda: encode_scan_telegram(scan, dialect)),
            "ms",
        ),
    ]


def main() -> None:
    scan = realistic_scan()
    for dialect in Dialect:
        for line in bench_dialect(dialect, scan):
            print(line)
    targets = {Dialect.COLA_A: 0.3, Dialect.COLA_B: 0.1}
    print(
        "targets (median, framing excluded): "
        + ", ".join(f"{d.value} <= {ms} ms" for d, ms in targets.items())
    )


if __name__ == "__main__":
    main()
