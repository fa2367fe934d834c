"""The Husky's route autopilot: the issue's figures, printed, never asserted.

Each run is `dbw sim track` (``appliance.sim.track_run``): the daemon's route chain and
the pedals speed controller on the simulated Husky (G_ss with V_char, servo lag and rate
limit, engine and brake lags), judged by the truth at the anchor.

1. Off-road miles (seeded: curvature changing all the time, arcs down to 15 m, 12 m
   clothoids between them), 10 mph set speed, fixes of sigma 5 cm at 10 Hz with the
   paper's 0.3 m switching jumps every 20 s: RMS and max cross-track at the anchor after
   the first 10 m, for the 4WS pure pursuit and for plain two-wheel pure pursuit (eq. 1
   from the rear axle, no k) on the same plant, and their ratio; the same without jumps,
   and with jumps that last (every 60 s: believed after 30 s, by design).
2. 0.5 m parallel offset at 10 mph: distance to below 0.1 m.
3. Speed hold at 10 mph on the mile: RMS speed error against the profile's target (the
   profile slows for 15 m arcs at a 1 m/s^2 lateral limit and stops at the end) and
   against the set speed.
4. One control step of the chain (planner + tracker + speed target, with the fix pairing
   and the transform) and of the pedals controller: median, p99, max over a mile.
5. The mile's real-time factor.

Run: ``python -m benchmarks.bench_tracking [SEEDS]`` (3 seeds by default).
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

import numpy as np

from appliance.config import load_config
from appliance.guidance.pedal_speed import PedalSpeedController
from appliance.guidance.route_follow import RouteFollower
from appliance.sim.courses import off_road_course, straight_course
from appliance.sim.track_run import TrackResult, TrackRunParams, run_track
from benchmarks.stats import summarize

MPH_10 = 4.47


def _mile(seed: int, **kw: object) -> TrackResult:
    params = replace(TrackRunParams(seed=seed, loc_noise_m=0.05), **kw)  # type: ignore[arg-type]
    return run_track(load_config("husky"), off_road_course(seed), params)


def _line(name: str, results: list[TrackResult]) -> str:
    rms = [r.rms_cross_track_m * 100 for r in results]
    worst = [r.max_cross_track_m * 100 for r in results]
    done = sum(r.reason == "end of course" for r in results)
    return (
        f"  {name}: RMS cross-track {', '.join(f'{v:.1f}' for v in rms)} cm "
        f"(mean {np.mean(rms):.1f}), max {', '.join(f'{v:.1f}' for v in worst)} cm; "
        f"completed {done}/{len(results)}"
    )


def step_timings(seed: int) -> tuple[list[float], list[float]]:
    """Wall time of each RouteFollower.update and PedalSpeedController.update in a mile."""
    chain: list[float] = []
    pedals: list[float] = []
    follow_update = RouteFollower.update
    pedal_update = PedalSpeedController.update

    def timed_follow(self: RouteFollower, *args: object, **kw: object) -> object:
        started = time.perf_counter()
        out = follow_update(self, *args, **kw)  # type: ignore[arg-type]
        chain.append(time.perf_counter() - started)
        return out

    def timed_pedals(self: PedalSpeedController, *args: object, **kw: object) -> object:
        started = time.perf_counter()
        out = pedal_update(self, *args, **kw)  # type: ignore[arg-type]
        pedals.append(time.perf_counter() - started)
        return out

    RouteFollower.update = timed_follow  # type: ignore[assignment,method-assign]
    PedalSpeedController.update = timed_pedals  # type: ignore[assignment,method-assign]
    try:
        _mile(seed, loc_jump_m=0.3)
    finally:
        RouteFollower.update = follow_update  # type: ignore[method-assign]
        PedalSpeedController.update = pedal_update  # type: ignore[method-assign]
    return chain, pedals


def main(argv: list[str] | None = None) -> int:
    seeds = list(range(1, 1 + (int(argv[0]) if argv else 3)))
    print(f"Husky route autopilot on the simulated vehicle, off-road miles, seeds {seeds}")
    print("1. cross-track at the anchor, 10 mph, fix sigma 5 cm at 10 Hz, after the first 10 m")
    four_ws = [_mile(s, loc_jump_m=0.3) for s in seeds]
    plain = [_mile(s, loc_jump_m=0.3, tracker="plain") for s in seeds]
    print(_line("4WS pure pursuit, 0.3 m jumps every 20 s", four_ws))
    print(_line("plain two-wheel pure pursuit, same", plain))
    ratio = np.mean(
        [p.rms_cross_track_m / f.rms_cross_track_m for p, f in zip(plain, four_ws, strict=True)]
    )
    print(f"  ratio plain / 4WS (RMS): {ratio:.1f}")
    print(_line("4WS, no jumps", [_mile(s) for s in seeds]))
    print(
        _line(
            "4WS, 0.3 m jumps every 60 s (believed after 30 s)",
            [_mile(s, loc_jump_m=0.3, loc_jump_period_s=60.0) for s in seeds],
        )
    )

    print("2. 0.5 m parallel offset at 10 mph, fix sigma 5 cm")
    offsets = [
        run_track(
            load_config("husky"),
            straight_course(120.0),
            TrackRunParams(offset_m=side * 0.5, seed=s, loc_noise_m=0.05),
        )
        for s in seeds
        for side in (1.0, -1.0)
    ]
    distances = [r.converge_distance_m for r in offsets]
    print(
        "  distance to below 0.1 m: "
        + ", ".join("never" if d is None else f"{d:.1f}" for d in distances)
        + " m"
    )

    print("3. speed hold, 10 mph set, on the miles with jumps")
    print(
        "  RMS speed error against the profile's target: "
        + ", ".join(f"{r.rms_speed_error_mps:.3f}" for r in four_ws)
        + " m/s; against the set speed: "
        + ", ".join(f"{r.rms_speed_error_vs_set_mps:.3f}" for r in four_ws)
        + " m/s; mean speed "
        + ", ".join(f"{r.mean_speed_mps:.2f}" for r in four_ws)
        + " m/s"
    )

    print("4. one control step")
    chain, pedals = step_timings(seeds[0])
    print(
        "  "
        + summarize(
            "route chain (fixes, transform, planner, tracker, speed target)",
            [c * 1e3 for c in chain],
            "ms",
        )
    )
    print("  " + summarize("pedals speed controller", [p * 1e3 for p in pedals], "ms"))
    both = np.asarray(chain) + np.asarray(
        pedals[: len(chain)] + [0.0] * max(0, len(chain) - len(pedals))
    )
    print("  " + summarize("both", list(both * 1e3), "ms"))

    print("5. real-time factor of the mile (world 100 Hz, control 50 Hz)")
    print("  " + ", ".join(f"{r.realtime_factor:.0f}x" for r in four_ws))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
