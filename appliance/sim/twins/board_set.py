"""All four simulated boards of one vehicle: what the daemon starts for ``sim://`` ports.

The ptys' stable paths live in one directory; ``port_path("sim://steering")`` is what the
client opens, exactly as it would open ``/dev/serial/by-id/...`` on the vehicle. The panel's
e-stop is wired to the actuator twins directly, not over serial, because on the vehicle it
is a hard-wired loop that no software sits in.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from appliance.config.models import VehicleConfig
from appliance.sim.twins.boards import BrakeTwin, PanelTwin, SteeringTwin, ThrottleTwin
from appliance.sim.world import SimWorld
from drivers.actuators.steering_model import PotMapping, ServoParams
from drivers.actuators.twin import BoardTwin
from drivers.ptylink import SIM_PORT_PREFIX


class ActuatorTwins:
    """All four boards of one simulated vehicle, their ptys in one directory.

    The daemon maps ``sim://steering`` to ``port_path("sim://steering")`` and gives that
    path to the client, exactly as it would give ``/dev/serial/by-id/...`` on the vehicle.
    """

    def __init__(
        self,
        world: SimWorld | None = None,
        directory: str | None = None,
        *,
        command_timeout_s: float = 0.1,
        telemetry_period_s: float = 0.01,
        servo_params: ServoParams | None = None,
        pot_mapping: PotMapping | None = None,
        encoder_offset_rad: float = 0.0,
        linkage_cubic: float = 0.0,
        seed: int = 0,
    ) -> None:
        self._own_directory = directory is None
        self.directory = directory or tempfile.mkdtemp(prefix="dbw-twins-")
        timing = {"command_timeout_s": command_timeout_s, "telemetry_period_s": telemetry_period_s}
        path = os.path.join
        self.steering = SteeringTwin(
            path(self.directory, "steering"),
            world,
            params=servo_params,
            pot_mapping=pot_mapping,
            encoder_offset_rad=encoder_offset_rad,
            linkage_cubic=linkage_cubic,
            seed=seed,
            **timing,
        )
        self.throttle = ThrottleTwin(path(self.directory, "throttle"), world, **timing)
        self.brake = BrakeTwin(path(self.directory, "brake"), world, **timing)
        self.panel = PanelTwin(path(self.directory, "panel"), on_estop=self._estop, **timing)
        self.boards: dict[str, BoardTwin[Any]] = {
            "steering": self.steering,
            "throttle": self.throttle,
            "brake": self.brake,
            "panel": self.panel,
        }

    @classmethod
    def from_config(
        cls, config: VehicleConfig, world: SimWorld | None, directory: str | None = None
    ) -> ActuatorTwins:
        steering = config.simulation.steering
        # The servo slews at least as fast as the vehicle file lets the daemon steer (and
        # as the simulated vehicle's own model turns its tyres): a servo slower than the
        # limit lags every hard turn until the tracking rule calls it a fault, which a real
        # installation avoids by setting limits.max_steer_rate_deg_per_s to what its servo
        # does.
        servo = ServoParams(steering_ratio=steering.steering_ratio)
        needed_rad_per_s = (
            1.1 * math.radians(config.limits.max_steer_rate_deg_per_s) * servo.steering_ratio
        )
        servo = replace(servo, max_rate_rad_per_s=max(servo.max_rate_rad_per_s, needed_rad_per_s))
        twins = cls(
            world,
            directory,
            command_timeout_s=config.safety.lower_layer_command_timeout_s,
            servo_params=servo,
            pot_mapping=PotMapping(centre_counts=steering.pot_centre_counts),
            encoder_offset_rad=steering.encoder_offset_rad,
            linkage_cubic=steering.linkage_cubic,
            seed=steering.pot_seed,
        )
        twins.throttle.pedal_drives_engine = config.speed_path == "pedals"
        return twins

    def port_path(self, port: str) -> str:
        """``sim://NAME`` -> the tty path (a stable symlink) the client should open."""
        name = port.removeprefix(SIM_PORT_PREFIX)
        if not port.startswith(SIM_PORT_PREFIX) or name not in self.boards:
            raise ValueError(f"no simulated board for port {port!r}; known: {list(self.boards)}")
        return self.boards[name].link.link_path

    def _estop(self, active: bool) -> None:
        for twin in (self.steering, self.throttle, self.brake):
            twin.set_estop(active)

    def step(self, now_s: float) -> None:
        for twin in self.boards.values():
            twin.step(now_s)

    async def run(
        self,
        clock: Callable[[], float] = time.monotonic,
        on_step: Callable[[], None] | None = None,
    ) -> None:
        """Step every board at the telemetry rate, in real time, until cancelled.

        On an absolute schedule, as the board's timer interrupt is: sleeping a period
        after each step would stretch every period by the step and the loop's latency
        (measured: 11.4 ms median for 10 ms), eating into the daemon's staleness margin.
        """
        period_s = self.steering.telemetry_period_s
        next_s = clock()
        while True:
            self.step(clock())
            if on_step is not None:
                on_step()
            next_s += period_s
            delay_s = next_s - clock()
            if delay_s < 0.0:  # overran a period: restart the schedule rather than burst
                next_s -= delay_s
                delay_s = 0.0
            await asyncio.sleep(delay_s)

    def close(self) -> None:
        for twin in self.boards.values():
            twin.close()
        if self._own_directory:
            with contextlib.suppress(OSError):
                shutil.rmtree(self.directory)
