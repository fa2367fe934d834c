"""The pedal sweep's maps against the simulated vehicle's own pedals, and what it costs.

Each run hides a pedal shape in the simulated Husky (``[simulation.pedals]``: a throttle
dead band 0..8 %, exponents 0.7..1.3 for the throttle and 1.0..1.5 for the brake, drawn
per seed), runs the vehicle file's full default sweep (``[pedal_sweep]``: three throttle
levels, a coast-down and five brake levels, top 4.2 m/s) faster than real time through
the same program, pedal limiter, actuator lag and GNSS speed the daemon has
(``appliance.sim.sweep_run``), fits it as `dbw calibrate pedals` does, and compares every
measured cell with ``appliance.sim.vehicle.pedal_accel_mps2``.

    python -m benchmarks.bench_pedal_sweep [RUNS]     # 20 by default, a second each

Figures, printed and never asserted: each map's largest error over its measured cells as
a percentage of the map's span at the lowest band (coasting to its top level; the issue's
goal is 5 %), and apart from them over the cells the fit filled in between measured
levels of a band (carried from the nearest band where the level was measured, along the
map's speed slope: the simulated vehicle's drag is the same for every pedal, so on it
the carry is all but exact; a real vehicle's is as good as that assumption),
the cells measured, whether the verdict accepted, the sweep's duration (what it takes on the
vehicle, in simulated seconds) and its distance. The daemon path is the runtime test's
(``tests/runtime/test_calibrate_pedals.py``, a short sweep); the full sweep through the
daemon is not measured here.
"""

from __future__ import annotations

import random
import sys

import numpy as np

from appliance.config import VehicleConfig, load_config
from appliance.maneuvers.pedals_step import PedalsStep
from appliance.maneuvers.steps import StepContext
from appliance.sim.sweep_run import full_scale_mps2, map_errors_mps2, run_sweep
from benchmarks.stats import summarize


def hidden_pedals(seed: int) -> VehicleConfig:
    rng = random.Random(seed)
    data = load_config("husky-sim").model_dump()
    data["simulation"]["pedals"] = {
        "throttle_deadband_pct": rng.uniform(0.0, 8.0),
        "throttle_exponent": rng.uniform(0.7, 1.3),
        "brake_deadband_pct": rng.uniform(0.0, 4.0),
        "brake_exponent": rng.uniform(1.0, 1.5),
    }
    return VehicleConfig.model_validate(data)


def main(runs: int = 20) -> None:
    errors: dict[str, list[float]] = {"throttle": [], "brake": []}
    filled: dict[str, list[float]] = {"throttle": [], "brake": []}
    cells: list[float] = []
    durations: list[float] = []
    distances: list[float] = []
    accepted = 0
    for seed in range(runs):
        config = hidden_pedals(seed)
        run = run_sweep(config)
        step = PedalsStep(StepContext(config, None))
        report = step.fit(run.samples, None)
        accepted += report.accepted
        result = step.accumulator.fit()
        for name, pedal_map in (("throttle", result.throttle), ("brake", result.brake)):
            brake = name == "brake"
            error = np.abs(map_errors_mps2(config, pedal_map, brake))
            span = full_scale_mps2(config, pedal_map, brake)
            errors[name].append(100.0 * float(np.max(error[pedal_map.measured])) / span)
            if pedal_map.filled.any():
                filled[name].append(100.0 * float(np.max(error[pedal_map.filled])) / span)
        cells.append(float(result.throttle.measured.sum() + result.brake.measured.sum()))
        durations.append(run.duration_s)
        distances.append(run.distance_m)
    print(f"pedal sweep, {runs} hidden pedal shapes, the full default sweep ({run.runs} runs)")
    for name, values in errors.items():
        print("  " + summarize(f"{name} map, measured cells, largest error", values, "% of span"))
        print(
            "  " + summarize(f"{name} map, filled cells, largest error", filled[name], "% of span")
        )
    print("  " + summarize("cells measured (both maps)", cells, ""))
    print("  " + summarize("sweep duration", durations, "s"))
    print("  " + summarize("sweep distance", distances, "m"))
    print(f"  verdict accepted in {accepted} of {runs} runs")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20)
