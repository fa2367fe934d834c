"""The simulated vehicle inline, for runtime tests that reach into its twins."""

from __future__ import annotations

import socket

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


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def isolated(config: VehicleConfig) -> VehicleConfig:
    """``config`` with its scanners on free ports: the profiles' fixed 2111/2112 are bound
    by any other simulated vehicle on this machine (a test beside this one, a scanner
    twin a test before it has not finished closing)."""
    devices = config.devices.model_copy(
        update={
            side: getattr(config.devices, side).model_copy(update={"port": free_port()})
            for side in ("lms111_left", "lms111_right")
        }
    )
    return config.model_copy(update={"devices": devices})
