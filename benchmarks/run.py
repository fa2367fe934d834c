"""`make bench`: run every benchmark and print its figures."""

from __future__ import annotations

import importlib
import sys
import time

BENCHMARKS = [
    "benchmarks.bench_wakeup",
    "benchmarks.bench_supervisor",
    "benchmarks.bench_sim_raycast",
    "benchmarks.bench_sim_twins",
    "benchmarks.bench_lms111_decode",
    "benchmarks.bench_actuators",
    "benchmarks.bench_lms111_stream",
    "benchmarks.bench_pc104",
    "benchmarks.bench_control",
    "benchmarks.bench_scanner_model",
    "benchmarks.bench_features",
    "benchmarks.bench_docking",
    "benchmarks.bench_pallet",
    "benchmarks.bench_tracking",
    "benchmarks.bench_pedal_sweep",
    "benchmarks.bench_lookahead",
    "benchmarks.bench_map_merge",
]


def main(argv: list[str]) -> int:
    selected = [b for b in BENCHMARKS if not argv or any(a in b for a in argv)]
    for name in selected:
        started = time.monotonic()
        importlib.import_module(name).main()
        print(f"({name} took {time.monotonic() - started:.1f} s)\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
