"""The supervisor against services that crash, hang, run slow and refuse to die."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from structlog.testing import capture_logs

from appliance.supervisor import ServiceContext, ServiceSpec, ServiceState, Supervisor
from safety.watchdog import RestartPolicy

FAST = RestartPolicy(initial_backoff_s=0.02, backoff_factor=2.0, backoff_cap_s=0.1, max_restarts=3)


@contextlib.asynccontextmanager
async def running(supervisor: Supervisor) -> AsyncIterator[asyncio.Task[None]]:
    task = asyncio.create_task(supervisor.run())
    try:
        yield task
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.wait_for(task, 2.0)


async def wait_until(predicate: Callable[[], bool], timeout_s: float = 3.0) -> None:
    async def poll() -> None:
        while not predicate():
            await asyncio.sleep(0.005)

    await asyncio.wait_for(poll(), timeout_s)


def beating(period_s: float = 0.01) -> Callable[[ServiceContext], Awaitable[None]]:
    async def run(ctx: ServiceContext) -> None:
        while True:
            ctx.beat()
            await asyncio.sleep(period_s)

    return run


def spec(name: str, run: Callable[[ServiceContext], Awaitable[None]], **kw: object) -> ServiceSpec:
    options: dict[str, object] = {"critical": True, "restart": FAST, "heartbeat_deadline_s": 0.1}
    options.update(kw)
    return ServiceSpec(name=name, run=run, **options)  # type: ignore[arg-type]


async def test_healthy_services_come_up_and_stay_healthy() -> None:
    sup = Supervisor([spec("a", beating()), spec("b", beating(), critical=False)])
    async with running(sup):
        await asyncio.wait_for(sup.wait_critical_up(), 1.0)
        await asyncio.sleep(0.3)
        assert sup.critical_healthy()
        assert all(s.state is ServiceState.RUNNING and s.restarts == 0 for s in sup.snapshot())


async def test_crashing_service_is_restarted_with_backoff_and_logged() -> None:
    starts: list[float] = []
    loop = asyncio.get_running_loop()

    async def flaky(ctx: ServiceContext) -> None:
        starts.append(loop.time())
        ctx.beat()
        if len(starts) <= 2:
            raise RuntimeError(f"boom {len(starts)}")
        await beating()(ctx)

    failures: list[str] = []
    sup = Supervisor([spec("flaky", flaky)], on_failure=lambda s, r: failures.append(r))
    with capture_logs() as logs:
        async with running(sup):
            await wait_until(lambda: len(starts) >= 3 and sup.critical_healthy())
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    assert gaps[0] >= 0.02 * 0.9 and gaps[1] >= 0.04 * 0.9  # exponential backoff
    assert failures == ["crashed: RuntimeError: boom 1", "crashed: RuntimeError: boom 2"]
    restarts = [e for e in logs if e["event"] == "service_restarting"]
    assert [e["reason"] for e in restarts] == failures
    assert [e["backoff_s"] for e in restarts] == [0.02, 0.04]


async def test_hung_service_is_cancelled_and_restarted() -> None:
    attempts = 0
    cancelled = 0

    async def hangs_once(ctx: ServiceContext) -> None:
        nonlocal attempts, cancelled
        attempts += 1
        ctx.beat()
        if attempts == 1:
            try:
                await asyncio.Event().wait()  # stops beating forever
            except asyncio.CancelledError:
                cancelled += 1
                raise
        await beating()(ctx)

    sup = Supervisor([spec("hangs", hangs_once)])
    with capture_logs() as logs:
        async with running(sup):
            await wait_until(lambda: attempts == 2 and sup.critical_healthy())
    assert cancelled == 1
    hung = [e for e in logs if e["event"] == "service_hung"]
    assert len(hung) == 1 and hung[0]["deadline_s"] == 0.1
    assert sup.records["hangs"].last_error.startswith("heartbeat missed")


async def test_slow_service_within_its_deadline_is_left_alone() -> None:
    sup = Supervisor([spec("slow", beating(0.06), heartbeat_deadline_s=0.1)])
    async with running(sup):
        await asyncio.sleep(0.5)
        assert sup.snapshot()[0].restarts == 0
        assert sup.critical_healthy()


async def test_slow_service_beyond_its_deadline_is_restarted() -> None:
    sup = Supervisor([spec("slow", beating(0.25), heartbeat_deadline_s=0.1)])
    async with running(sup):
        await wait_until(lambda: sup.records["slow"].budget.total_restarts >= 1)
    assert "heartbeat missed" in sup.records["slow"].last_error


async def test_no_first_heartbeat_within_grace_is_a_hang() -> None:
    async def never_beats(ctx: ServiceContext) -> None:
        await asyncio.sleep(10)

    sup = Supervisor([spec("mute", never_beats, startup_grace_s=0.05)])
    async with running(sup):
        await wait_until(lambda: sup.records["mute"].budget.total_restarts >= 1)
    assert "no first heartbeat" in sup.records["mute"].last_error


async def test_returning_service_counts_as_failure() -> None:
    async def returns(ctx: ServiceContext) -> None:
        ctx.beat()

    sup = Supervisor([spec("quitter", returns, critical=False)])
    async with running(sup):
        await wait_until(lambda: sup.records["quitter"].state is ServiceState.FAILED)
    assert sup.records["quitter"].last_error == "returned unexpectedly"


async def test_critical_service_exhausting_restarts_latches_error() -> None:
    async def always_crashes(ctx: ServiceContext) -> None:
        raise ValueError("sensor on fire")

    sup = Supervisor([spec("control", always_crashes), spec("other", beating(), critical=False)])
    with capture_logs() as logs:
        async with running(sup):
            await wait_until(lambda: sup.latched_error is not None)
            assert not sup.critical_healthy()
            await asyncio.sleep(0.1)
            assert sup.records["other"].state is ServiceState.RUNNING  # others keep running
    latched = sup.latched_error
    assert latched is not None and latched.service == "control"
    assert "sensor on fire" in latched.reason
    assert sup.records["control"].budget.total_restarts == FAST.max_restarts
    assert [e["event"] for e in logs].count("critical_service_failed") == 1


async def test_non_critical_failure_does_not_latch() -> None:
    async def always_crashes(ctx: ServiceContext) -> None:
        raise ValueError("nope")

    sup = Supervisor([spec("control", beating()), spec("extra", always_crashes, critical=False)])
    async with running(sup):
        await wait_until(lambda: sup.records["extra"].state is ServiceState.FAILED)
        assert sup.latched_error is None
        assert sup.critical_healthy()


async def test_service_that_ignores_cancellation_stays_hung_and_unhealthy() -> None:
    released = False

    async def stubborn(ctx: ServiceContext) -> None:
        ctx.beat()
        while not released:
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.sleep(0.01)
        await asyncio.sleep(1)  # now cancellable again

    sup = Supervisor([spec("stubborn", stubborn)], cancel_timeout_s=0.05)
    task = asyncio.create_task(sup.run())
    with capture_logs() as logs:
        await wait_until(lambda: sup.records["stubborn"].state is ServiceState.HUNG)
        await asyncio.sleep(0.2)
    assert not sup.critical_healthy()
    assert any(e["event"] == "service_stuck" for e in logs)
    # The daemon exits hard in this case; here the test lets it go to clean up.
    released = True
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await asyncio.wait_for(task, 2.0)


def test_critical_service_must_have_a_heartbeat() -> None:
    with pytest.raises(ValueError, match="heartbeat deadline"):
        ServiceSpec(name="c", run=beating(), critical=True, restart=FAST)


def test_service_names_are_unique() -> None:
    with pytest.raises(ValueError, match="unique"):
        Supervisor([spec("a", beating()), spec("a", beating())])


async def test_permanent_failure_is_not_retried() -> None:
    from appliance.supervisor import PermanentServiceError

    runs = 0

    async def refuses(ctx: ServiceContext) -> None:
        nonlocal runs
        runs += 1
        raise PermanentServiceError("scanner refused its configuration: invalid data")

    sup = Supervisor([spec("scanner", refuses, critical=False)])
    async with running(sup):
        await wait_until(lambda: sup.records["scanner"].state is ServiceState.FAILED)
    assert runs == 1
    assert "refused its configuration" in sup.records["scanner"].last_error
