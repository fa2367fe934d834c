"""The supervisor: one task group that owns every service of the daemon.

Each service is a coroutine ``run(ctx)`` that beats ``ctx.beat()`` while it works. The
supervisor starts it inside a task group of its own together with a heartbeat watcher, so
whatever ends the run (a crash, a missed heartbeat, a stop request) ends both tasks and
nothing outlives its parent. Restart decisions live here, in one place, with the budget
and backoff from :mod:`safety.watchdog`.

Health, as systemd's watchdog sees it: every critical service is running with a fresh
heartbeat, or is being restarted within its budget. A service that stopped beating and
will not even acknowledge cancellation stays HUNG, and a critical service that exhausted
its restarts latches an error; either way the daemon stops petting the systemd watchdog
so the whole process is restarted (it then comes up at best READY, never engaged).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from enum import StrEnum

from appliance.logs import get_logger
from safety.watchdog import Heartbeat, RestartBudget, RestartPolicy

log = get_logger("supervisor")

Clock = Callable[[], float]
PERMANENT_PREFIX = "permanent failure: "


class ServiceState(StrEnum):
    STARTING = "starting"  # started, no heartbeat yet
    RUNNING = "running"  # has beaten at least once
    HUNG = "hung"  # missed its heartbeat; being cancelled
    BACKOFF = "backoff"  # failed; waiting to restart
    FAILED = "failed"  # restart budget exhausted; will not run again
    STOPPED = "stopped"  # stopped on request


class HeartbeatMissed(Exception):
    """Raised by the watcher to end a run whose service stopped beating."""


class PermanentServiceError(Exception):
    """Raised by a service whose failure a restart cannot fix (a device refusing its
    configuration, a refused login): the supervisor gives up at once instead of looping."""


class ServiceExited(Exception):
    """A daemon service returned although nobody asked it to stop."""


async def _cancel_and_join(tasks: set[asyncio.Future[None]]) -> None:
    """Cancel tasks and wait until every one has ended, even if we are cancelled meanwhile."""
    stop_requested = False
    while True:
        for task in tasks:
            task.cancel()
        try:
            await asyncio.wait(tasks)
            break
        except asyncio.CancelledError:
            stop_requested = True
    for task in tasks:  # mark every outcome as seen; _run_once reads the ones it needs
        if not task.cancelled():
            task.exception()
    if stop_requested:
        raise asyncio.CancelledError


class ServiceContext:
    """What a running service gets from its supervisor."""

    def __init__(self, record: ServiceRecord, clock: Clock) -> None:
        self._record = record
        self._clock = clock
        self.name = record.spec.name

    def beat(self) -> None:
        """Prove liveness; the first beat also marks the service as up."""
        record = self._record
        record.heartbeat.beat(self._clock())
        if record.state is ServiceState.STARTING:
            record.state = ServiceState.RUNNING
            log.info("service_up", service=self.name, attempt=record.attempt)


@dataclass(frozen=True)
class ServiceSpec:
    """A service, its criticality and the deadlines the supervisor holds it to."""

    name: str
    run: Callable[[ServiceContext], Awaitable[None]]
    critical: bool
    restart: RestartPolicy
    # None: no heartbeat monitoring; the service is alive while its coroutine runs.
    heartbeat_deadline_s: float | None = None
    # Time allowed before the first beat (connecting to a device may take a while).
    startup_grace_s: float | None = None

    def __post_init__(self) -> None:
        if self.critical and self.heartbeat_deadline_s is None:
            raise ValueError(
                f"critical service {self.name!r} needs a heartbeat deadline: the systemd "
                "watchdog is only as good as the liveness it is told about"
            )


def beating_service(
    name: str,
    run: Callable[[Callable[[], None]], Awaitable[None]],
    policy: RestartPolicy,
    deadline_s: float,
    *,
    critical: bool = False,
    startup_grace_s: float | None = None,
) -> ServiceSpec:
    """A service from a driver's ``run(beat)``: drivers know nothing of the supervisor."""

    async def adapter(ctx: ServiceContext) -> None:
        await run(ctx.beat)

    return ServiceSpec(
        name=name,
        run=adapter,
        critical=critical,
        restart=policy,
        heartbeat_deadline_s=deadline_s,
        startup_grace_s=startup_grace_s,
    )


@dataclass
class ServiceRecord:
    spec: ServiceSpec
    heartbeat: Heartbeat
    budget: RestartBudget
    state: ServiceState = ServiceState.STARTING
    attempt: int = 0
    started_s: float = 0.0
    state_since_s: float = 0.0
    last_error: str = ""
    failure_log: list[tuple[float, str]] = field(default_factory=list)


@dataclass(frozen=True)
class ServiceStatus:
    name: str
    critical: bool
    state: ServiceState
    restarts: int
    heartbeat_age_s: float
    last_error: str


@dataclass(frozen=True)
class LatchedError:
    service: str
    reason: str
    at_s: float


FailureHook = Callable[[ServiceSpec, str], None]


class Supervisor:
    """Runs services, restarts them by policy and reports their health."""

    def __init__(
        self,
        specs: list[ServiceSpec],
        *,
        clock: Clock = time.monotonic,
        cancel_timeout_s: float = 0.5,
        on_failure: FailureHook | None = None,
    ) -> None:
        names = [spec.name for spec in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"service names must be unique: {names}")
        self._clock = clock
        self._cancel_timeout_s = cancel_timeout_s
        self._on_failure = on_failure
        self.records: dict[str, ServiceRecord] = {
            spec.name: ServiceRecord(
                spec=spec,
                heartbeat=Heartbeat(spec.heartbeat_deadline_s or 1.0),
                budget=RestartBudget(spec.restart),
            )
            for spec in specs
        }
        self.latched_error: LatchedError | None = None
        self._critical_up = asyncio.Event()
        self._changed = asyncio.Event()

    # ---- running -----------------------------------------------------------------
    async def run(self) -> None:
        """Run every service until cancelled; a cancellation stops them all."""
        async with asyncio.TaskGroup() as group:
            for record in self.records.values():
                group.create_task(self._supervise(record), name=f"supervise:{record.spec.name}")
            group.create_task(self._watch_critical_up(), name="supervise:ready")

    async def _supervise(self, record: ServiceRecord) -> None:
        spec = record.spec
        try:
            while True:
                record.attempt += 1
                record.heartbeat.reset()
                record.started_s = self._clock()
                self._set_state(
                    record,
                    ServiceState.STARTING
                    if spec.heartbeat_deadline_s is not None
                    else ServiceState.RUNNING,
                )
                reason = await self._run_once(record)
                ran_for_s = self._clock() - record.started_s
                record.last_error = reason
                record.failure_log.append((self._clock(), reason))
                del record.failure_log[:-20]
                if self._on_failure is not None:
                    self._on_failure(spec, reason)
                delay_s = (
                    None
                    if reason.startswith(PERMANENT_PREFIX)
                    else record.budget.on_failure(ran_for_s)
                )
                if delay_s is None:
                    self._give_up(record, reason)
                    return
                self._set_state(record, ServiceState.BACKOFF)
                log.warning(
                    "service_restarting",
                    service=spec.name,
                    critical=spec.critical,
                    reason=reason,
                    ran_for_s=round(ran_for_s, 3),
                    backoff_s=round(delay_s, 3),
                    restart=record.budget.restarts_in_episode,
                    max_restarts=spec.restart.max_restarts,
                )
                await asyncio.sleep(delay_s)
        except asyncio.CancelledError:
            if record.state is not ServiceState.FAILED:
                self._set_state(record, ServiceState.STOPPED)
            raise

    async def _run_once(self, record: ServiceRecord) -> str:
        """Run the service once beside its heartbeat watcher; return why it ended.

        Both tasks belong to this call: whatever ends first, the ``finally`` cancels the
        other and waits for both, so nothing outlives the run. (An inner TaskGroup would
        do the same, but on Python 3.11 it can swallow a stop request that arrives while
        a child is failing.) A service that ignores cancellation keeps us waiting here,
        in state HUNG, which is exactly what the systemd watchdog must see.
        """
        ctx = ServiceContext(record, self._clock)
        tasks: set[asyncio.Future[None]] = {
            asyncio.create_task(self._call(record, ctx), name=record.spec.name)
        }
        if record.spec.heartbeat_deadline_s is not None:
            tasks.add(
                asyncio.create_task(
                    self._watch_heartbeat(record), name=f"{record.spec.name}:watchdog"
                )
            )
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            await _cancel_and_join(tasks)
        errors = [task.exception() for task in tasks if not task.cancelled() and task.exception()]
        for error in errors:
            if isinstance(error, HeartbeatMissed):
                return str(error)
        for error in errors:
            if isinstance(error, ServiceExited):
                return "returned unexpectedly"
        if not errors:
            return "ended without an error"
        error = errors[0]
        while isinstance(error, ExceptionGroup):  # a service's own task group failed
            error = error.exceptions[0]
        if isinstance(error, PermanentServiceError):
            log.error("service_failed_permanently", service=record.spec.name, error=str(error))
            return f"{PERMANENT_PREFIX}{error}"
        log.error(
            "service_crashed",
            service=record.spec.name,
            error=f"{type(error).__name__}: {error}",
            exc_info=error,
        )
        return f"crashed: {type(error).__name__}: {error}"

    async def _call(self, record: ServiceRecord, ctx: ServiceContext) -> None:
        await record.spec.run(ctx)
        raise ServiceExited

    async def _watch_heartbeat(self, record: ServiceRecord) -> None:
        spec = record.spec
        assert spec.heartbeat_deadline_s is not None
        grace_s = (
            spec.startup_grace_s if spec.startup_grace_s is not None else spec.heartbeat_deadline_s
        )
        while True:
            last_s = record.heartbeat.last_beat_s
            expires_s = (
                record.started_s + grace_s if last_s is None else last_s + spec.heartbeat_deadline_s
            )
            now_s = self._clock()
            if now_s > expires_s:
                age_s = record.heartbeat.age_s(now_s)
                self._set_state(record, ServiceState.HUNG)
                log.error(
                    "service_hung",
                    service=spec.name,
                    critical=spec.critical,
                    heartbeat_age_s=None if last_s is None else round(age_s, 3),
                    deadline_s=spec.heartbeat_deadline_s,
                )
                self._warn_if_stuck(record)
                what = "no first heartbeat" if last_s is None else "heartbeat missed"
                silent_s = now_s - (record.started_s if last_s is None else last_s)
                raise HeartbeatMissed(
                    f"{what} for {silent_s:.3f} s (deadline {spec.heartbeat_deadline_s} s)"
                )
            await asyncio.sleep(max(expires_s - now_s, 0.0) + 1e-4)

    def _warn_if_stuck(self, record: ServiceRecord) -> None:
        """Log once if a hung service does not acknowledge its cancellation in time."""
        loop = asyncio.get_running_loop()
        attempt = record.attempt

        def check() -> None:
            if record.state is ServiceState.HUNG and record.attempt == attempt:
                log.critical(
                    "service_stuck",
                    service=record.spec.name,
                    critical=record.spec.critical,
                    cancel_timeout_s=self._cancel_timeout_s,
                    consequence="systemd watchdog pings stop"
                    if record.spec.critical
                    else "degraded",
                )

        loop.call_later(self._cancel_timeout_s, check)

    def _give_up(self, record: ServiceRecord, reason: str) -> None:
        self._set_state(record, ServiceState.FAILED)
        spec = record.spec
        if spec.critical and self.latched_error is None:
            self.latched_error = LatchedError(spec.name, reason, self._clock())
            log.critical(
                "critical_service_failed",
                service=spec.name,
                reason=reason,
                restarts=record.budget.total_restarts,
                consequence="latched error state",
            )
        else:
            log.error(
                "service_given_up",
                service=spec.name,
                critical=spec.critical,
                reason=reason,
                restarts=record.budget.total_restarts,
            )

    def _set_state(self, record: ServiceRecord, state: ServiceState) -> None:
        if record.state is not state:
            record.state = state
            record.state_since_s = self._clock()
            self._changed.set()

    async def _watch_critical_up(self) -> None:
        while not self.all_critical_up():
            self._changed.clear()
            await self._wait_changed_or(0.01)
        self._critical_up.set()

    async def _wait_changed_or(self, timeout_s: float) -> None:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._changed.wait(), timeout_s)

    # ---- health ------------------------------------------------------------------
    def all_critical_up(self) -> bool:
        return all(
            record.state is ServiceState.RUNNING
            for record in self.records.values()
            if record.spec.critical
        )

    async def wait_critical_up(self) -> None:
        await self._critical_up.wait()

    def critical_healthy(self, now_s: float | None = None) -> bool:
        """Whether systemd's watchdog may be petted now (see the module docstring)."""
        if self.latched_error is not None:
            return False
        now_s = self._clock() if now_s is None else now_s
        for record in self.records.values():
            if not record.spec.critical:
                continue
            if record.state in (ServiceState.STARTING, ServiceState.BACKOFF):
                continue  # being (re)started within its budget
            if record.state is not ServiceState.RUNNING:
                return False
            deadline_s = record.spec.heartbeat_deadline_s
            if deadline_s is not None and not record.heartbeat.is_alive(now_s):
                return False
        return True

    def snapshot(self, now_s: float | None = None) -> list[ServiceStatus]:
        now_s = self._clock() if now_s is None else now_s
        return [
            ServiceStatus(
                name=record.spec.name,
                critical=record.spec.critical,
                state=record.state,
                restarts=record.budget.total_restarts,
                heartbeat_age_s=record.heartbeat.age_s(now_s),
                last_error=record.last_error,
            )
            for record in self.records.values()
        ]
