"""Staleness limits for long engaged runs of the shipped profiles on a shared test machine.

Why: the shipped profiles keep the limits a vehicle gets (the steering pot 50 ms, five
telemetry periods of the board). On the vehicle the board is a microcontroller; here its
twin is a niced Python process on two cores shared with the daemon, the raycasting
scanner twins, pytest and whatever else the CI host runs. Measured on this project's VMs
with four busy processes beside a route test, the pot's longest gap between two frames
at the daemon was 39-41 ms when the twin slept a period after each step, 24.5 ms on its
absolute schedule (11.8 ms on an idle machine); a CI run saw 51 ms, and the daemon,
rightly, went to ERROR mid-route. A test of docking or route following is not a test of
the host's scheduler, so these runs get limits a few times wider. Detection of stale
inputs is tested with the shipped limits elsewhere (tests/runtime/test_daemon_control.py,
test_actuator_boards.py).
"""

from __future__ import annotations

from appliance.config import VehicleConfig

# Each at least twice the longest gap measured under load, and still well under a second:
# a stopped twin is found out within these, as on the vehicle.
SHARED_MACHINE_LIMITS_S = {
    "steering_pot_max_age_s": 0.15,
    "actuator_board_max_age_s": 0.2,
    "panel_max_age_s": 0.3,
    "scan_max_age_s": 0.25,
    "pose_max_age_s": 0.25,
    "pc104_status_max_age_s": 0.25,
}


def for_shared_machine(config: VehicleConfig) -> VehicleConfig:
    """``config`` with each staleness limit widened to ``SHARED_MACHINE_LIMITS_S`` (never
    narrowed: a profile's own wider limit stays)."""
    current = config.staleness.model_dump()
    update = {name: max(current[name], limit) for name, limit in SHARED_MACHINE_LIMITS_S.items()}
    return config.model_copy(update={"staleness": config.staleness.model_copy(update=update)})
