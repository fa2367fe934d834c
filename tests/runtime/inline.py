"""The simulated vehicle inline, for runtime tests that reach into its twins."""

from __future__ import annotations

from appliance.config import VehicleConfig
from appliance.config.models import SimPlacement


def inline_sim(config: VehicleConfig) -> VehicleConfig:
    """``config`` with its simulated vehicle in this process, so a test can reach its twins.

    An inline simulation shares the daemon's event loop, so the steering pot gets the
    80 ms that the sim profile had before the twins moved to their own process.
    """
    simulation = config.simulation.model_copy(update={"placement": SimPlacement.INLINE})
    staleness = config.staleness.model_copy(update={"steering_pot_max_age_s": 0.08})
    return config.model_copy(update={"simulation": simulation, "staleness": staleness})
