"""A recording of the `pallet` source carries the worker's map it read: the replay's core
gets that map (not whatever file the path names on the replaying machine), or the
recorded reason there was none."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.config import load_config
from appliance.config.models import VehicleConfig
from appliance.core.pallet_autopilot import PalletAutopilot
from appliance.recording.replay import ReplayError, core_from_metadata, worker_map_metadata
from appliance.recording.service import session_metadata


def _metadata(config: VehicleConfig, source: PalletAutopilot) -> dict[str, dict[str, str]]:
    metadata = session_metadata(config, "", "calibration missing", 0)
    metadata.update(worker_map_metadata(source))
    return metadata


def test_the_replay_uses_the_recorded_map_not_the_file(tmp_path: Path) -> None:
    recorded = load_config("forklift-sim")
    source = PalletAutopilot(recorded)
    # The vehicle file named a file that is not on the machine that replays.
    gone = recorded.pallets.model_copy(update={"worker_map": str(tmp_path / "gone.json")})
    metadata = _metadata(recorded.model_copy(update={"pallets": gone}), source)
    core = core_from_metadata(metadata)
    replayed = core.autopilot
    assert isinstance(replayed, PalletAutopilot) and not replayed.worker_problem
    assert replayed.worker is not None and source.worker is not None
    for a, b in zip(replayed.worker.pallets, source.worker.pallets, strict=True):
        assert (a.x_m, a.y_m, a.yaw_rad, a.kind, a.name) == (
            b.x_m,
            b.y_m,
            b.yaw_rad,
            b.kind,
            b.name,
        )
        assert np.array_equal(a.covariance, b.covariance)


def test_a_map_that_did_not_load_replays_as_not_loaded(tmp_path: Path) -> None:
    missing = tmp_path / "worker.ply"
    config = load_config("forklift-sim")
    config = config.model_copy(
        update={"pallets": config.pallets.model_copy(update={"worker_map": str(missing)})}
    )
    source = PalletAutopilot(config)
    assert source.worker is None and "cannot read it" in source.worker_problem
    metadata = _metadata(config, source)
    missing.write_text('{"frame": "worker", "objects": []}')  # there now, not then
    replayed = core_from_metadata(metadata).autopilot
    assert isinstance(replayed, PalletAutopilot)
    assert replayed.worker is None and replayed.worker_problem == source.worker_problem


def test_a_damaged_recorded_map_is_a_replay_error_naming_it() -> None:
    config = load_config("forklift-sim")
    source = PalletAutopilot(config)
    for key in ("json", "alternatives_json"):
        metadata = _metadata(config, source)
        metadata["dbw.worker_map"][key] = '{"pallets": [1, 2'  # cut short
        with pytest.raises(ReplayError, match="the recorded worker's map does not load"):
            core_from_metadata(metadata)
