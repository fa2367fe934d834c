"""The daemon end to end: systemd notifications, watchdog gating, safe stop, signals."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable

import pytest

from appliance.config import VehicleConfig, load_config
from appliance.daemon import Daemon, safe_command
from appliance.supervisor import ServiceContext, ServiceSpec
from safety.safe_stop import SafeCommand, SafeStop
from safety.watchdog import RestartPolicy
from tests.runtime.inline import isolated
from tools.fake_notify import FakeNotifySocket

WATCHDOG_S = 0.4  # pings every 0.2 s


class RecordingTarget:
    """An actuator path that records what it was told."""

    name = "recorder"

    def __init__(self) -> None:
        self.calls: list[tuple[SafeCommand, str]] = []

    def command_safe_state(self, command: SafeCommand, reason: str) -> None:
        self.calls.append((command, reason))


def make_daemon(
    monkeypatch: pytest.MonkeyPatch,
    notify: FakeNotifySocket,
    extra: list[ServiceSpec] | None = None,
    config: VehicleConfig | None = None,
) -> tuple[Daemon, RecordingTarget]:
    for key, value in notify.environment(WATCHDOG_S).items():
        monkeypatch.setenv(key, value)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    config = config or isolated(load_config("sim"))
    target = RecordingTarget()
    daemon = Daemon(
        config,
        extra_services=extra,
        safe_stop=SafeStop(safe_command(config), [target]),
        # A socket of this test's own, not the config's relative var/dbw/control.sock that
        # any other daemon started from the same directory would be serving too.
        control_socket=str(notify.path.parent / "control.sock"),
    )
    return daemon, target


def record_pings(monkeypatch: pytest.MonkeyPatch, daemon: Daemon) -> list[tuple[float, bool]]:
    """Each WATCHDOG ping as the daemon sends it: its time, and whether an error was latched.

    The fake socket's arrival times lag the sends by a scheduling delay (tens of ms on a
    loaded machine), so when a ping was sent is judged here, not from its arrival.
    """
    sent: list[tuple[float, bool]] = []
    ping = daemon.notifier.watchdog

    def recorded_ping() -> None:
        sent.append((daemon.clock(), daemon.supervisor.latched_error is not None))
        ping()

    monkeypatch.setattr(daemon.notifier, "watchdog", recorded_ping)
    return sent


async def until(condition: Callable[[], bool], timeout_s: float = 20.0) -> None:
    """Wait (without blocking the loop) for ``condition``; the bound is only a safety net."""
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.005)


def hanging_service(
    trigger: asyncio.Event,
    *,
    ignore_cancel: bool,
    hung_at: list[float],
    release: asyncio.Event | None = None,
) -> Callable[[ServiceContext], Awaitable[None]]:
    """Beats until ``trigger``, then hangs once; ``release`` lets a stubborn hang end."""

    async def run(ctx: ServiceContext) -> None:
        while not trigger.is_set():
            ctx.beat()
            await asyncio.sleep(0.01)
        if not hung_at:
            hung_at.append(time.monotonic())
            if ignore_cancel:
                assert release is not None
                while not release.is_set():  # neither beats nor lets itself be cancelled
                    with contextlib.suppress(asyncio.CancelledError):
                        await asyncio.sleep(0.01)
            await asyncio.Event().wait()
        while True:  # after a restart: healthy again
            ctx.beat()
            await asyncio.sleep(0.01)

    return run


async def test_ready_watchdog_status_and_stopping(
    monkeypatch: pytest.MonkeyPatch, notify_socket: FakeNotifySocket
) -> None:
    daemon, target = make_daemon(monkeypatch, notify_socket)
    result = await daemon.run(duration_s=1.2, handle_signals=False)
    assert result.exit_code == 0
    notify_socket.wait_for("STOPPING=1", timeout_s=1.0)
    lines = [m.line for m in notify_socket.messages]
    assert lines.count("READY=1") == 1
    ready_index = lines.index("READY=1")
    pings = [m for m in notify_socket.lines("WATCHDOG=1")]
    assert 3 <= len(pings) <= 8, lines  # every WATCHDOG_S / 2 for ~1.2 s
    assert all(lines.index("WATCHDOG=1") > ready_index for _ in pings)
    gaps = [b.at_s - a.at_s for a, b in itertools.pairwise(pings)]
    assert max(gaps) < WATCHDOG_S  # never close to letting systemd fire
    assert any(line.startswith(("STATUS=READY", "STATUS=SELF_CHECK")) for line in lines)
    stopping = notify_socket.wait_for("STOPPING=1", timeout_s=1.0)
    assert all(p.at_s <= stopping.at_s for p in notify_socket.lines("WATCHDOG=1"))
    notify_socket.wait_for("STATUS=stopping: ran for the requested 1.2 s", timeout_s=1.0)
    assert target.calls and target.calls[-1][0].throttle_pct == 0.0
    assert "shutdown" in target.calls[-1][1]


async def test_watchdog_stops_for_good_when_a_critical_service_is_stuck(
    monkeypatch: pytest.MonkeyPatch, notify_socket: FakeNotifySocket
) -> None:
    trigger = asyncio.Event()
    release = asyncio.Event()
    hung_at: list[float] = []
    policy = RestartPolicy(initial_backoff_s=0.01, max_restarts=3)
    stuck = ServiceSpec(
        name="planner",
        run=hanging_service(trigger, ignore_cancel=True, hung_at=hung_at, release=release),
        critical=True,
        restart=policy,
        heartbeat_deadline_s=0.1,
    )
    daemon, target = make_daemon(monkeypatch, notify_socket, [stuck])
    sent = record_pings(monkeypatch, daemon)
    run = asyncio.ensure_future(daemon.run(duration_s=None, handle_signals=False))
    await asyncio.to_thread(notify_socket.wait_for, "WATCHDOG=1")
    trigger.set()
    await until(lambda: bool(hung_at))
    # Watch for more than a second beyond the heartbeat deadline, however long the loaded
    # machine takes: until the status service, still running, has beaten that late.
    status = daemon.supervisor.records["status"].heartbeat
    await until(lambda: (status.last_beat_s or 0.0) > hung_at[0] + 0.1 + 1.0)
    # The last ping may precede the hang; none is sent later than the heartbeat deadline,
    # and none since.
    assert sent[-1][0] <= hung_at[0] + 0.1
    await asyncio.to_thread(notify_socket.wait_for, "STATUS=DEGRADED", 10.0)
    daemon.request_stop("test over")
    # The stuck task cannot be joined: the daemon reports that the process must exit hard.
    result = await asyncio.wait_for(run, 2.0)
    assert result.must_force_exit
    assert any("shutdown" in reason for _, reason in target.calls)
    release.set()  # the real daemon exits hard here; the test lets the task end instead
    await asyncio.sleep(0.05)


async def test_watchdog_pauses_and_resumes_around_a_restarted_hang(
    monkeypatch: pytest.MonkeyPatch, notify_socket: FakeNotifySocket
) -> None:
    trigger = asyncio.Event()
    hung_at: list[float] = []
    spec = ServiceSpec(
        name="planner",
        run=hanging_service(trigger, ignore_cancel=False, hung_at=hung_at),
        critical=True,
        restart=RestartPolicy(initial_backoff_s=0.01, max_restarts=3),
        heartbeat_deadline_s=0.1,
    )
    daemon, target = make_daemon(monkeypatch, notify_socket, [spec])
    run = asyncio.ensure_future(daemon.run(duration_s=None, handle_signals=False))
    await asyncio.to_thread(notify_socket.wait_for, "WATCHDOG=1")
    trigger.set()
    await until(lambda: bool(hung_at))
    # Pings must resume once the service is healthy again: wait for one, not for a time.
    await asyncio.to_thread(notify_socket.wait_for, "WATCHDOG=1", 10.0, hung_at[0] + 0.1)
    daemon.request_stop("test over")
    result = await asyncio.wait_for(run, 2.0)
    assert result.exit_code == 0 and not result.must_force_exit
    assert daemon.supervisor.records["planner"].budget.total_restarts == 1
    # The critical failure held the vehicle safe before anything else happened.
    assert any("critical service planner failed" in reason for _, reason in target.calls)


async def test_latched_error_withholds_watchdog_and_holds_safe(
    monkeypatch: pytest.MonkeyPatch, notify_socket: FakeNotifySocket
) -> None:
    async def broken(ctx: ServiceContext) -> None:
        ctx.beat()
        await asyncio.sleep(0.05)
        raise OSError("servo board unplugged")

    spec = ServiceSpec(
        name="actuators",
        run=broken,
        critical=True,
        restart=RestartPolicy(initial_backoff_s=0.01, backoff_cap_s=0.02, max_restarts=2),
        heartbeat_deadline_s=0.5,
    )
    daemon, target = make_daemon(monkeypatch, notify_socket, [spec])
    # A ping sent just before the latch may arrive after it: judge the sends.
    sent = record_pings(monkeypatch, daemon)
    run = asyncio.ensure_future(daemon.run(duration_s=None, handle_signals=False))
    # Not a fixed run time: however long the start-up and the three failures take, wait
    # for the latch, then until the status service has run a whole ping period beyond it
    # (it would have pinged by then if it still thought the daemon healthy).
    await until(lambda: daemon.supervisor.latched_error is not None)
    latched = daemon.supervisor.latched_error
    assert latched is not None
    status = daemon.supervisor.records["status"].heartbeat
    await until(lambda: (status.last_beat_s or 0.0) > latched.at_s + WATCHDOG_S)
    error = await asyncio.to_thread(notify_socket.wait_for, "STATUS=ERROR", 10.0)
    daemon.request_stop("test over")
    result = await asyncio.wait_for(run, 5.0)
    assert result.exit_code == 0
    assert "servo board unplugged" in error.line
    assert not [at_s for at_s, after_latch in sent if after_latch]
    assert all(at_s <= latched.at_s for at_s, _ in sent)
    notify_socket.wait_for("STOPPING=1")  # every earlier datagram has arrived too
    assert len(notify_socket.lines("WATCHDOG=1")) == len(sent)  # no ping but these
    failures = [r for _, r in target.calls if "critical service actuators failed" in r]
    assert len(failures) == 3  # the first run and both restarts


async def test_second_signal_forces_exit_after_safe_stop(
    monkeypatch: pytest.MonkeyPatch, notify_socket: FakeNotifySocket
) -> None:
    released = asyncio.Event()

    async def slow_to_stop(ctx: ServiceContext) -> None:
        while True:
            ctx.beat()
            try:
                await asyncio.sleep(0.01)
            except asyncio.CancelledError:
                await released.wait()  # takes its time to unwind
                raise

    spec = ServiceSpec(
        name="slow",
        run=slow_to_stop,
        critical=False,
        restart=RestartPolicy(),
        heartbeat_deadline_s=1.0,
    )
    daemon, target = make_daemon(monkeypatch, notify_socket, [spec])
    exits: list[int] = []
    monkeypatch.setattr("appliance.daemon.os._exit", exits.append)
    run = asyncio.ensure_future(daemon.run(duration_s=None, handle_signals=True))
    await asyncio.to_thread(notify_socket.wait_for, "READY=1")
    os.kill(os.getpid(), signal.SIGTERM)
    await asyncio.sleep(0.05)
    os.kill(os.getpid(), signal.SIGINT)
    await asyncio.sleep(0.05)
    assert exits == [128 + signal.SIGINT]
    assert any("forced exit" in reason for _, reason in target.calls)
    released.set()
    await asyncio.wait_for(run, 2.0)


def _spawn_daemon(notify: FakeNotifySocket) -> subprocess.Popen[str]:
    env = dict(os.environ)
    env.update(notify.environment())
    return subprocess.Popen(
        [sys.executable, "-m", "appliance", "--log-format", "json", "run", "--config", "sim"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_stops_the_process_within_one_second(
    notify_socket: FakeNotifySocket, signum: signal.Signals
) -> None:
    proc = _spawn_daemon(notify_socket)
    try:
        notify_socket.wait_for("READY=1", timeout_s=20)
        time.sleep(0.3)
        sent_s = time.monotonic()
        proc.send_signal(signum)
        proc.wait(timeout=5)
        stopped_s = time.monotonic() - sent_s
    finally:
        if proc.poll() is None:
            proc.kill()
    out, err = proc.communicate()
    assert proc.returncode == 0, err
    assert stopped_s < 1.0, f"took {stopped_s:.3f} s"
    notify_socket.wait_for("STOPPING=1", timeout_s=1)
    events = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    names = [e["event"] for e in events]
    assert names.index("signal_received") < names.index("safe_stop") < names.index("daemon_stopped")
    safe = events[names.index("safe_stop")]
    assert (safe["throttle_pct"], safe["brake_pct"], safe["steering"]) == (0.0, 100.0, "released")
    assert signum.name in safe["reason"]
    assert all("task" in e and "mono_s" in e for e in events)
