"""The daemon: the supervisor, the systemd conversation, signals and the way out.

Every way out of ``run`` passes through one ``finally`` that engages the safe-stop hook,
whether the stop was asked for (SIGTERM, SIGINT, a bounded demo), a service crashed, or
the daemon's own code failed. Shutdown is bounded: services get ``shutdown_grace_s`` to
unwind; a task that ignores cancellation is abandoned (and the process exits hard) rather
than allowed to hold the vehicle's software hostage. A second signal exits at once,
after telling the actuators to go safe one more time.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from appliance.config import VehicleConfig
from appliance.config.calibration import Calibration, CalibrationFile
from appliance.config.calibration_file import (
    BUILTIN_SIMULATED,
    CalibrationError,
    dumps_calibration,
    read_vehicle_calibration,
)
from appliance.control_loop import ControlLoop, OperatorWatch, TopicInputs
from appliance.control_socket import ControlServer
from appliance.core.autopilot import AutopilotSource
from appliance.core.core import ControlCore
from appliance.core.jobs import ThreadJobs
from appliance.core.output import CoreOutput
from appliance.core.pallet_autopilot import PalletAutopilot
from appliance.daemon_status import service_summary, status_document, status_line
from appliance.live_view import LiveView
from appliance.logs import get_logger
from appliance.loop_monitor import LoopLag, LoopMonitor
from appliance.operator_page import OperatorPage, scans_document
from appliance.recording.replay import worker_map_metadata
from appliance.recording.service import Recorder
from appliance.sim.scanner_truth import with_simulated_scanners
from appliance.supervisor import ServiceContext, ServiceSpec, ServiceState, Supervisor
from appliance.system_monitor import SYSTEM_HEALTH_TOPIC, SystemMonitor
from appliance.systemd_notify import SystemdNotifier
from appliance.tablet_page.service import TABLET_TOPIC, TabletService
from appliance.vehicle_io import (
    VehicleCommandSink,
    VehicleIO,
    build_vehicle_io,
    input_ages_s,
    link_summary,
    pc104_link_counts,
)
from drivers.topics import Topic
from safety.safe_stop import SafeCommand, SafeStop
from safety.watchdog import RestartPolicy

log = get_logger("daemon")

EXIT_OK = 0
SWITCH_INTERVAL_S = 0.001
# The recorder beats with each status line of its process (1 Hz); starting it is an
# interpreter and its imports.
RECORDER_HEARTBEAT_DEADLINE_S = 5.0
RECORDER_STARTUP_GRACE_S = 15.0
OPERATOR_PAGE_HEARTBEAT_DEADLINE_S = 5.0  # it beats once a second
EXIT_FAILURE = 1


def restart_policy(config: VehicleConfig) -> RestartPolicy:
    sup = config.supervision
    return RestartPolicy(
        initial_backoff_s=sup.restart_initial_backoff_s,
        backoff_factor=sup.restart_backoff_factor,
        backoff_cap_s=sup.restart_backoff_cap_s,
        max_restarts=sup.max_restarts,
        budget_reset_after_s=sup.restart_budget_reset_after_s,
    )


def safe_command(config: VehicleConfig) -> SafeCommand:
    return SafeCommand(
        throttle_pct=0.0,
        brake_pct=config.limits.brake_max_pct,
        decel_mps2=config.safety.safe_stop_decel_mps2,
    )


@dataclass(frozen=True)
class RunResult:
    exit_code: int
    reason: str
    # True when a task ignored cancellation: the caller must end the process with os._exit.
    must_force_exit: bool = False


class Daemon:
    """Owns the supervisor and everything between it and the operating system."""

    def __init__(
        self,
        config: VehicleConfig,
        *,
        extra_services: list[ServiceSpec] | None = None,
        safe_stop: SafeStop | None = None,
        notifier: SystemdNotifier | None = None,
        vehicle_io: VehicleIO | None = None,
        clock: Callable[[], float] = time.monotonic,
        autopilot: AutopilotSource | None = None,
        control_socket: str | None = None,
        record: bool | None = None,
    ) -> None:
        self.config = config
        self.clock = clock
        self.started_s = clock()
        self.safe_stop = safe_stop if safe_stop is not None else SafeStop(safe_command(config))
        self.notifier = notifier if notifier is not None else SystemdNotifier()
        policy = restart_policy(config)
        self.io = vehicle_io if vehicle_io is not None else build_vehicle_io(config, policy)
        for target in self.io.safe_stop_targets:
            self.safe_stop.add_target(target)
        calibration_model, problem = load_vehicle_calibration_file(config)
        calibration = (
            None if calibration_model is None else Calibration.from_file(calibration_model)
        )
        self.core = ControlCore(config, calibration, problem, autopilot=autopilot)
        # A source with work longer than a cycle (the pallet source's merge and plans)
        # gets a worker thread; when the work is done is read into each cycle's inputs.
        self.jobs: ThreadJobs | None = None
        if isinstance(self.core.autopilot, PalletAutopilot):
            self.jobs = self.core.autopilot.jobs = ThreadJobs()
        self.control = ControlLoop(
            self.core,
            TopicInputs(
                self.io.topics,
                lambda: pc104_link_counts(self.io),
                self._critical_service_faults,
                None if self.jobs is None else self.jobs.done,
            ),
            config.rates.control_hz,
            clock=clock,
        )
        self.control.sinks.append(
            VehicleCommandSink(self.io, self.control.lease_s, self._display_note)
        )
        self.io.work_slot.attach(self.control.ticker)
        watch = OperatorWatch(
            self.control.ticker.wake_early, config.safety.pedal_override_margin_pct
        )
        self.io.topics.get("board.panel").subscribe(watch.on_panel)
        for pedal in ("brake", "throttle"):
            self.io.topics.get(f"board.{pedal}").subscribe(watch.on_pedal(pedal))
        # The status topic: every cycle's output (mode, commands, notes), for recorders and
        # any in-process consumer; `dbw status` is its view from outside the process.
        self.status_topic: Topic[CoreOutput] = Topic("control.status")
        self.io.topics.register(self.status_topic.name, self.status_topic)
        self.control.on_output.append(self._publish_status)
        # The PC's own health, probed off the loop; an input the core judges (off: None).
        self.system_monitor: SystemMonitor | None = None
        if config.system_monitor.enabled:
            self.system_monitor = SystemMonitor(config, clock=clock)
            self.io.topics.register(SYSTEM_HEALTH_TOPIC, self.system_monitor.topic)
        # The Foxglove live view, on its own threads; fed only while someone watches.
        self.live_view: LiveView | None = None
        if config.live_view.enabled:
            self.live_view = LiveView(config, time.time_ns() - time.monotonic_ns())
            self.live_view.attach(self.io.topics)
            self.live_view.route_window = getattr(self.core.autopilot, "route_window", None)
            self.control.on_cycle.append(self.live_view.on_cycle)
        # The flight recorder: every sample, cycle and request, to MCAP (off: None).
        self.recorder: Recorder | None = None
        if record if record is not None else config.recording.enabled:
            self.recorder = Recorder(
                config,
                "" if calibration_model is None else dumps_calibration(calibration_model),
                calibration_problem=problem,
                clock=clock,
            )
            if isinstance(self.core.autopilot, PalletAutopilot):
                # The worker's map as the source read it: a replay elsewhere needs no file.
                self.recorder.metadata.update(worker_map_metadata(self.core.autopilot))
            self.recorder.attach(self.io.topics)
            self.recorder.attach_raw(self.io.raw_sources())
            self.control.on_cycle.append(self.recorder.on_cycle)
            self.control.on_start.append(self.recorder.on_core_reset)
            self.core.request_listeners.append(self.recorder.on_request)
        # The operator page: a read-only browser view of the status (off: None).
        self.operator_page: OperatorPage | None = None
        if config.operator_page.enabled:
            settings = config.operator_page
            self.operator_page = OperatorPage(
                self.status_document,
                lambda: scans_document(self.io.topics, self.clock()),
                settings.host,
                settings.port,
                allow_non_loopback=settings.allow_non_loopback,
            )
        # The tablet page: a worker's tablet guides a forklift (off: None). Its topic is
        # registered after the recorder attached: the core's inputs carry the hold into
        # every recorded cycle, which is all a replay needs.
        self.tablet: TabletService | None = None
        if config.tablet_page.enabled:
            self.tablet = TabletService(
                config.tablet_page,
                self.clock,
                self.control.ticker.wake_early,
                self._tablet_state,
                self.core.select_pallet,
            )
            self.io.topics.register(TABLET_TOPIC, self.tablet.topic)
        self.control_server = ControlServer(
            control_socket if control_socket is not None else config.paths.control_socket,
            DaemonControlApi(self),
        )
        specs = [
            ServiceSpec(
                name="control",
                run=self.control.run,
                critical=True,
                restart=policy,
                heartbeat_deadline_s=config.supervision.control_heartbeat_deadline_s,
            ),
            *self.io.services,
            *(extra_services or []),
            ServiceSpec(
                name="control_socket",
                run=self.control_server.run,
                critical=False,
                restart=policy,
                heartbeat_deadline_s=2.0,
            ),
            ServiceSpec(
                name="status",
                run=self._status_service,
                critical=False,
                restart=policy,
            ),
            *(
                []
                if self.system_monitor is None
                else [
                    ServiceSpec(
                        name="system_monitor",
                        run=self.system_monitor.run,
                        critical=False,
                        restart=policy,
                    )
                ]
            ),
            *(
                []
                if self.live_view is None
                else [
                    ServiceSpec(
                        name="live_view",
                        run=self.live_view.run,
                        critical=False,
                        restart=policy,
                    )
                ]
            ),
            *(
                []
                if self.operator_page is None
                else [
                    ServiceSpec(
                        name="operator_page",
                        run=self.operator_page.run,
                        critical=False,
                        restart=policy,
                        heartbeat_deadline_s=OPERATOR_PAGE_HEARTBEAT_DEADLINE_S,
                    )
                ]
            ),
            *(
                []
                if self.tablet is None
                else [
                    ServiceSpec(
                        name="tablet_page",
                        run=self.tablet.page.run,
                        critical=False,
                        restart=policy,
                        heartbeat_deadline_s=OPERATOR_PAGE_HEARTBEAT_DEADLINE_S,
                    )
                ]
            ),
            *(
                []
                if self.recorder is None
                else [
                    ServiceSpec(
                        name="recorder",
                        run=self.recorder.run,
                        critical=False,
                        restart=policy,
                        heartbeat_deadline_s=RECORDER_HEARTBEAT_DEADLINE_S,
                        startup_grace_s=RECORDER_STARTUP_GRACE_S,
                    )
                ]
            ),
        ]
        self.supervisor = Supervisor(
            specs,
            clock=clock,
            cancel_timeout_s=config.supervision.cancel_timeout_s,
            on_failure=self._on_service_failure,
        )
        self.watchdog_pings = 0
        # Who holds the event loop: the longest callback of each heartbeat window, by name.
        self.loop_monitor = LoopMonitor()
        self.last_loop_lag: LoopLag | None = None
        self._stop_requested: asyncio.Event | None = None
        self._stop_reason = ""
        self._signals_seen = 0
        self._was_healthy = True
        self._stopping = False

    # ---- lifecycle ---------------------------------------------------------------
    async def run(self, duration_s: float | None = None, handle_signals: bool = True) -> RunResult:
        loop = asyncio.get_running_loop()
        # python-can's receive threads (and, in simulation, the twins' helpers) share the
        # GIL with the event loop; by default a busy thread keeps it for up to 5 ms, a
        # quarter of a 50 Hz cycle. Let the loop thread back in after 1 ms.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        if not self.loop_monitor.install(loop):
            log.warning("loop_monitor_disabled", reason=self.loop_monitor.disabled_reason)
        self._stop_requested = asyncio.Event()
        if handle_signals:
            for signum in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(signum, self._on_signal, signum)
        log.info(
            "daemon_starting",
            vehicle=self.config.name,
            kind=str(self.config.kind),
            simulation=self.config.simulation.enabled,
            services=list(self.supervisor.records),
            systemd=self.notifier.enabled,
            watchdog_interval_s=self.notifier.watchdog_interval_s,
        )
        self.notifier.status("starting services")
        # The one root task: every service lives below it, in the supervisor's task group.
        root: asyncio.Future[object] = asyncio.create_task(self.supervisor.run(), name="supervisor")
        result = RunResult(EXIT_FAILURE, "daemon failed before its services ran")
        try:
            result = await self._wait_for_end(root, duration_s)
        finally:
            try:
                result = await self._shut_down(root, result)
            finally:
                self.io.close()
                self.loop_monitor.uninstall()
                if self.jobs is not None:
                    self.jobs.close()
            if handle_signals:
                for signum in (signal.SIGTERM, signal.SIGINT):
                    loop.remove_signal_handler(signum)
        return result

    async def _wait_for_end(
        self, root: asyncio.Future[object], duration_s: float | None
    ) -> RunResult:
        assert self._stop_requested is not None
        stop_wait: asyncio.Future[object] = asyncio.ensure_future(self._stop_requested.wait())
        waited: set[asyncio.Future[object]] = {root, stop_wait}
        try:
            done, _ = await asyncio.wait(
                waited,
                timeout=duration_s,
                return_when=asyncio.FIRST_COMPLETED,
            )
        finally:
            stop_wait.cancel()
        if root in done:
            error = root.exception()
            reason = f"services ended: {error!r}" if error else "every service ended"
            log.critical("daemon_services_ended", reason=reason)
            return RunResult(EXIT_FAILURE, reason)
        if stop_wait in done:
            return RunResult(EXIT_OK, self._stop_reason)
        return RunResult(EXIT_OK, f"ran for the requested {duration_s} s")

    async def _shut_down(self, root: asyncio.Future[object], result: RunResult) -> RunResult:
        started_s = self.clock()
        self._stopping = True
        self.notifier.stopping()
        self.notifier.status(f"stopping: {result.reason}")
        log.info("daemon_stopping", reason=result.reason)
        # Command the safe state while the links to the actuators are still up; the
        # lower layers' own command timeouts take over once the drivers are gone. The
        # control loop stops sending first, so no later cycle overwrites it.
        self.control.halt()
        self.safe_stop.engage(f"shutdown: {result.reason}")
        # Periodic senders (the PC104 command) transmit the safe command on their next tick.
        await asyncio.sleep(2.0 / self.config.rates.pc104_command_hz)
        if self.recorder is not None:  # its last file finished, with the safe stop in it
            await self.recorder.close()
        root.cancel()
        grace_s = self.config.safety.shutdown_grace_s
        done, _ = await asyncio.wait({root}, timeout=grace_s)
        if root in done and not root.cancelled() and root.exception() is not None:
            log.error("daemon_root_error", error=repr(root.exception()))
        stuck = [
            name
            for name, record in self.supervisor.records.items()
            if record.state not in (ServiceState.STOPPED, ServiceState.FAILED)
        ]
        if root not in done:
            log.critical("daemon_services_did_not_stop", grace_s=grace_s, stuck=stuck)
            result = RunResult(EXIT_FAILURE, result.reason + "; services did not stop", True)
        log.info(
            "daemon_stopped",
            reason=result.reason,
            exit_code=result.exit_code,
            shutdown_s=round(self.clock() - started_s, 3),
            restarts=sum(r.budget.total_restarts for r in self.supervisor.records.values()),
            watchdog_pings=self.watchdog_pings,
        )
        return result

    def request_stop(self, reason: str) -> None:
        if self._stop_requested is not None and not self._stop_requested.is_set():
            self._stop_reason = reason
            self._stop_requested.set()

    def _on_signal(self, signum: int) -> None:
        self._signals_seen += 1
        name = signal.Signals(signum).name
        if self._signals_seen == 1:
            log.info("signal_received", signal=name, action="stopping cleanly")
            self.request_stop(name)
            return
        log.critical("signal_received", signal=name, action="forced exit")
        self.control.halt()
        self.safe_stop.engage(f"forced exit on second signal {name}")
        os._exit(128 + signum)

    def _publish_status(self, output: CoreOutput) -> None:
        self.status_topic.publish(output, output.now_s)

    # ---- supervision hooks -------------------------------------------------------
    def _critical_service_faults(self) -> dict[str, str]:
        """Critical services that are not running: a fault for the core (ERROR, held safe)."""
        faults = {}
        for status in self.supervisor.snapshot():
            running = status.state is ServiceState.RUNNING
            if status.critical and status.name != "control" and not running:
                why = f": {status.last_error}" if status.last_error else ""
                faults[status.name] = f"{status.state}{why}"
        return faults

    def _on_service_failure(self, spec: ServiceSpec, reason: str) -> None:
        if spec.critical:
            self.safe_stop.engage(f"critical service {spec.name} failed: {reason}")

    async def _status_service(self, ctx: ServiceContext) -> None:
        """READY once critical services are up; then WATCHDOG, STATUS and heartbeat logs."""
        await self.supervisor.wait_critical_up()
        # Everything allocated during start-up (config, protocol tables, numpy, the DBC)
        # lives as long as the process: move it out of the collector's view, so a full
        # collection scans only what the running loop allocates (a shorter pause).
        gc.freeze()
        self.notifier.ready()
        log.info("daemon_ready", services=self._service_summary())
        ping_period_s = (
            self.notifier.watchdog_interval_s / 2
            if self.notifier.watchdog_interval_s is not None
            else None
        )
        report_period_s = 1.0 / self.config.rates.status_report_hz
        tick_s = min(ping_period_s or math.inf, report_period_s, 0.1)
        last_ping_s = -math.inf
        last_report_s = self.clock()
        while True:
            now_s = self.clock()
            healthy = self.supervisor.critical_healthy(now_s)
            if healthy != self._was_healthy:
                self._was_healthy = healthy
                (log.info if healthy else log.error)(
                    "watchdog_pings_resumed" if healthy else "watchdog_pings_withheld",
                    services=self._service_summary(),
                )
            if self._stopping:
                ctx.beat()
                await asyncio.sleep(tick_s)
                continue
            if ping_period_s is not None and healthy and now_s - last_ping_s >= ping_period_s:
                self.notifier.watchdog()
                self.watchdog_pings += 1
                last_ping_s = now_s
            self.notifier.status(self.status_line())
            if now_s - last_report_s >= report_period_s:
                last_report_s = now_s
                await self.io.work_slot.clear()  # a heartbeat can wait for the cycle due
                jitter = self.control.ticker.stats.report()
                lag = self.loop_monitor.take_window()
                self.last_loop_lag = lag
                if lag.longest_ms >= 1e3 / self.config.rates.control_hz:
                    log.warning(
                        "event_loop_stalled",
                        longest_callback_ms=round(lag.longest_ms, 3),
                        process_cpu_pct=round(lag.cpu_pct, 1),
                        by=lag.longest_by,
                        slow_callbacks=lag.slow_callbacks,
                    )
                log.info(
                    "heartbeats",
                    mode=str(self.core.state.mode),
                    faults=[f.reason for f in self.core.state.faults],
                    services=self._service_summary(),
                    control_cycles=jitter.cycles,
                    control_overruns=jitter.overruns,
                    control_jitter_p99_ms=round(jitter.jitter_p99_ms, 3),
                    control_step_p99_ms=round(self.control.step_times.p99_ms(), 3),
                    input_ages_s=input_ages_s(self.io, now_s),
                    links=link_summary(self.io),
                    event_loop=lag.as_dict(),
                    watchdog_pings=self.watchdog_pings,
                )
            ctx.beat()
            await asyncio.sleep(tick_s)

    def _service_summary(self) -> dict[str, str]:
        return service_summary(self.supervisor.snapshot())

    def status_line(self) -> str:
        """One line for `systemctl status`: what the daemon is doing, in words."""
        return status_line(self.supervisor.latched_error, self.supervisor.snapshot(), self.core)

    def _display_note(self) -> str:
        """The panel's addition: the tablet's pairing code while none is paired."""
        return "" if self.tablet is None else self.tablet.display_note()

    def _tablet_state(self) -> dict[str, Any]:
        """What the tablet draws: the mode, and the pallet source's map, plan and pose
        where the vehicle has one (`state_for_tablet`)."""
        document: dict[str, Any] = {"mode": str(self.core.state.mode).upper().replace("_", " ")}
        source_state = getattr(self.core.autopilot, "state_for_tablet", None)
        if callable(source_state):
            document.update(source_state())
        return document

    def status_document(self) -> dict[str, Any]:
        """What `dbw status` shows: the core's view plus inputs, loop figures, services."""
        now_s = self.clock()
        return status_document(
            vehicle=self.config.name,
            uptime_s=now_s - self.started_s,
            core=self.core,
            topics=self.io.topics,
            loop=self.control.loop_figures(),
            work_deferred=self.io.work_slot.deferred,
            event_loop=self.last_loop_lag or self.loop_monitor.window(),
            event_loop_worst=self.loop_monitor.worst(),
            services=self._service_summary(),
            now_s=now_s,
            links=link_summary(self.io),
            gnss=None if self.io.gnss is None else self.io.gnss.status(now_s),
            recording=None if self.recorder is None else self.recorder.status(),
            system=None if self.system_monitor is None else self.system_monitor.status(now_s),
            tablet=None if self.tablet is None else self.tablet.status(),
        )


class DaemonControlApi:
    """The control socket's view of the daemon (status, and bench requests to the core)."""

    def __init__(self, daemon: Daemon) -> None:
        self._daemon = daemon

    def status(self) -> dict[str, Any]:
        return self._daemon.status_document()

    def request(self, name: str) -> tuple[bool, str]:
        return self._daemon.core.request(name, self._daemon.clock())

    def select_route(self, name: str) -> tuple[bool, str]:
        return self._daemon.core.select_route(name)

    def maneuver(self, action: str, step: str) -> tuple[bool, str]:
        return self._daemon.core.maneuver_request(action, step, self._daemon.clock())

    def bad_request(self, line: str, error: str) -> None:
        """A refused request line, told to the request listeners (the recorder) so a
        recording holds every input; replay counts it and changes nothing."""
        now_s = self._daemon.clock()
        for listener in self._daemon.core.request_listeners:
            listener("bad_request", line, now_s, False, error)

    def samples(self, since: int, limit: int) -> dict[str, Any]:
        return self._daemon.core.maneuver.samples_since(since, limit)


def load_vehicle_calibration(config: VehicleConfig) -> tuple[Calibration | None, str]:
    """The calibration, or None and why: the daemon still runs, but will not leave SELF_CHECK."""
    model, problem = load_vehicle_calibration_file(config)
    return (None if model is None else Calibration.from_file(model)), problem


def load_vehicle_calibration_file(config: VehicleConfig) -> tuple[CalibrationFile | None, str]:
    """The validated calibration file (what the recorder keeps), or None and why."""
    path = config.paths.calibration_file
    try:
        model = read_vehicle_calibration(config, path)
        if str(path) == BUILTIN_SIMULATED:
            model = with_simulated_scanners(model, config)
    except CalibrationError as exc:
        log.error("calibration_invalid", path=path, problems=exc.render())
        return None, f"calibration {path}: " + "; ".join(str(p) for p in exc.problems)
    log.info("calibration_loaded", path=path, source=str(path))
    return model, ""


def run_daemon(
    config: VehicleConfig, duration_s: float | None = None, record: bool | None = None
) -> int:
    """Entry point for `dbw run`: run until stopped, exit hard if a task refused to stop.

    ``asyncio.run`` would wait forever for a task that ignores cancellation, so the hard
    exit happens inside the loop, after the safe-stop hook has already run.
    """

    async def main() -> int:
        current = asyncio.current_task()
        if current is not None:
            current.set_name("daemon")
        result = await Daemon(config, record=record).run(duration_s=duration_s)
        if result.must_force_exit:
            with contextlib.suppress(Exception):
                sys.stdout.flush()
            os._exit(result.exit_code)
        return result.exit_code

    return asyncio.run(main())
