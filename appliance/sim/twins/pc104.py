"""The PC104 twin on a python-can bus: the simulated controller as a CAN node.

:class:`Pc104Twin` runs :class:`~appliance.sim.twins.pc104_core.Pc104TwinCore` on any python-can
bus: in the daemon's process on ``virtual`` (the built-in simulation and the runtime
tests), or as a separate process on socketcan/vcan for hardware-in-the-loop tests::

    python -m appliance.sim.twins.pc104 --interface socketcan --channel vcan0 [--seconds N]

It keeps ticking through link failures, like a real controller whose cable was pulled:
the vehicle goes on being simulated (and braked once commands stop) while the bus is
reopened with backoff. When it owns its world (``step_world``, always so from the
command line) it steps the world in real time on the same tick.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import signal
import sys
import time
from collections.abc import Callable, Sequence

import can

from appliance.config import load_config
from appliance.config.models import CanEndpoint
from appliance.logs import configure_logging, get_logger
from appliance.sim.twins.pc104_core import OutFrame, Pc104TwinCore, TwinFaults, TwinParams
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from appliance.timing import FixedRateTicker
from drivers.pc104 import protocol
from drivers.pc104.endpoint import CanInterface
from drivers.pc104.link import BusFactory, BusLink, Episode, LinkLost, bus_factory

log = get_logger("pc104.twin")


class Pc104Twin:
    def __init__(
        self,
        open_bus: BusFactory,
        world: SimWorld,
        *,
        step_world: bool = True,
        params: TwinParams | None = None,
        faults: TwinFaults | None = None,
        emit_error_frames: bool = False,
        tick_s: float = 0.005,
        reopen_backoff_cap_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        seed: int = 0,
    ) -> None:
        self.world = world
        self.step_world = step_world
        self.tick_s = tick_s
        self.reopen_backoff_cap_s = reopen_backoff_cap_s
        self._open_bus = open_bus
        self._clock = clock
        self.core = Pc104TwinCore(
            world,
            params or TwinParams(),
            faults,
            emit_error_frames=emit_error_frames,
            seed=seed,
            now_s=clock(),
        )
        self.send_drops = 0
        self.link_losses = 0
        self._ep_link = Episode(log, "pc104_twin_link_down")
        self._ep_drops = Episode(log, "pc104_twin_send_drops")

    @property
    def faults(self) -> TwinFaults:
        return self.core.faults

    def restart(self) -> None:
        """Simulate a reboot of the PC104: counters restart at 0, STOP required again."""
        self.core.restart(self._clock())
        log.info("pc104_twin_restarted", restarts=self.core.restarts)

    async def run(self) -> None:
        """Run until cancelled."""
        ticker = FixedRateTicker(self.tick_s, self._clock)
        world_offset_s = self._clock() - self.world.state.t_s
        link: BusLink | None = None
        retry_s, backoff_s = -math.inf, self.tick_s
        log.info("pc104_twin_started", dbc=protocol.DATABASE.version)
        try:
            while True:
                now_s = await ticker.tick()
                if link is None and now_s >= retry_s:
                    try:
                        link = BusLink(self._open_bus())
                    except (can.CanError, OSError, ValueError) as exc:
                        self._ep_link.occur(now_s, error=f"cannot open the bus: {exc}")
                        retry_s, backoff_s = now_s + backoff_s, self._next_backoff(backoff_s)
                try:
                    if link is not None:
                        self._receive(link, now_s)
                    if self.step_world:
                        self.world.advance_to(now_s - world_offset_s)
                    frames = self.core.tick(now_s)
                    if link is not None:
                        self._transmit(link, frames, now_s)
                except LinkLost as exc:
                    assert link is not None
                    self.link_losses += 1
                    self._ep_link.occur(now_s, error=str(exc))
                    link.close()
                    link = None
                    retry_s, backoff_s = now_s + backoff_s, self._next_backoff(backoff_s)
        finally:
            if link is not None:
                await link.aclose()
            log.info("pc104_twin_stopped", frames_sent=self.core.frames_sent)

    def _next_backoff(self, backoff_s: float) -> float:
        return min(backoff_s * 2, self.reopen_backoff_cap_s)

    def _receive(self, link: BusLink, now_s: float) -> None:
        link.check()
        while (message := link.poll()) is not None:
            if not (message.is_error_frame or message.is_extended_id or message.is_remote_frame):
                self.core.on_frame(message.arbitration_id, bytes(message.data), now_s)

    def _transmit(self, link: BusLink, frames: Sequence[OutFrame], now_s: float) -> None:
        for frame in frames:
            if link.send(frame.arbitration_id, frame.data, is_error_frame=frame.is_error_frame):
                self._ep_drops.clear(now_s, total_drops=self.send_drops)
                self._ep_link.clear(now_s, link_losses=self.link_losses)
            else:
                self.send_drops += 1
                self._ep_drops.occur(now_s, error=str(link.last_send_error))


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m appliance.sim.twins.pc104",
        description="Run the simulated PC104 controller with its own simulated vehicle.",
    )
    parser.add_argument("--interface", choices=[i.value for i in CanInterface], default="socketcan")
    parser.add_argument("--channel", default="vcan0")
    parser.add_argument("--seconds", type=float, default=None, help="stop after N s (default: run)")
    parser.add_argument("--config", default="sim", help="vehicle profile or TOML file (sim)")
    parser.add_argument("--log-level", default="info")
    return parser.parse_args(argv)


async def _run_for(twin: Pc104Twin, seconds: float | None) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    async with asyncio.TaskGroup() as group:
        runner = group.create_task(twin.run(), name="pc104-twin")
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), seconds)
        runner.cancel()


def main(argv: Sequence[str] | None = None) -> int:
    args = _parse_args(argv)
    configure_logging(args.log_level, stream=sys.stderr, json=True)
    config = load_config(args.config)
    world = SimWorld(VehicleParams.from_config(config), step_hz=config.simulation.world_step_hz)
    endpoint = CanEndpoint(interface=CanInterface(args.interface), channel=args.channel)
    twin = Pc104Twin(
        bus_factory(endpoint, protocol.HL_IDS),
        world,
        emit_error_frames=endpoint.interface is CanInterface.VIRTUAL,
    )
    asyncio.run(_run_for(twin, args.seconds))
    return 0


if __name__ == "__main__":
    sys.exit(main())
