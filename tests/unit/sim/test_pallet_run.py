"""`dbw sim pallet` end to end: the worker's map, the merge, the plan and the approach
with the pallet detected again, on the simulated forklift (one trial: ~10 s)."""

from __future__ import annotations

import json
import math

from click.testing import CliRunner

from appliance.cli.main import cli


def test_trial_3_puts_the_forks_at_the_pallet_within_the_papers_figures() -> None:
    result = CliRunner().invoke(cli, ["sim", "pallet", "--trial", "3", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.output)
    assert document["success"] and document["phase"] == "done"
    # The figure: 10 mm and 0.3 deg (the paper's worst: 10.3 mm and 0.35 deg).
    assert document["translation_error_mm"] <= 10.0
    assert abs(document["fork_angle_error_deg"]) <= 0.3
    assert document["vehicle_pallets"] >= 3 and document["worker_pallets"] >= 10
    assert math.isfinite(document["merge_error_mm"]) and document["merge_error_mm"] < 50.0


def test_a_vehicle_that_is_not_a_forklift_is_refused() -> None:
    result = CliRunner().invoke(cli, ["sim", "pallet", "--config", "flatbed-sim"])
    assert result.exit_code == 2
    assert "forklift" in result.output
