"""The simulated LMS111: a TCP server on 127.0.0.1 that the client cannot tell from the device.

`Lms111Twin` wraps the sans-I/O `DeviceModel` (what the device answers) in an asyncio
server (how it answers): any number of connections, both CoLa dialects (``sWN
EIHstCola`` switches the device; the answer still goes out in the old one), scans streamed
at the configured rate on an absolute schedule so counters and device time advance exactly
one period per scan, rendered by `appliance.sim.render_scan` from a pose source.

Requests it cannot read are answered as an LMS1xx does: a CoLa-A frame cut off by a new STX
before its ETX is dropped without a word (a CoLa-B request, such as the ``02 02 02 02 ...``
dialect probe SICK's ``sick_scan_xd`` starts with, looks exactly like that to a CoLa-A
device, and an LMS100 stays silent to it: sick_scan_xd #419), counted in
`TwinStats.truncated_requests`; any other unreadable telegram gets ``sFA 11`` (invalid
CoLa-A character) in CoLa-A and ``sFA 5`` in CoLa-B.

Faults are what users of LMS1xx drivers report from the field, so the client can be tested
against each (`TwinFaults`, changeable while running, plus `drop_connections`,
`stall_connections`, `report_not_ready`, and `stop`/`start` on the same port):

* link drops (``drop_connections``: RST) and silent stalls (the socket stays open and
  nothing comes: a half-open TCP connection after a switch reboot, clearpath LMS1xx #23);
* telegrams split across reads and several per read (``fragment``, ``batch_telegrams``);
* line noise between telegrams, a corrupted CoLa-B checksum, a truncated CoLa-A telegram;
* ``sFA`` to a named command, a refused login, a slow boot (TCP refused, or accepted and
  silent, for ``boot_s``), ``STlms`` not ready for a while, a reboot (``stop``/``start``:
  counters and the µs clock restart, as after a power cycle).

If the event loop falls far behind (more than `MAX_CATCH_UP_SCANS` periods), the missed scans
are counted but not sent, as a device with a full output buffer would do: the client sees a
scan counter gap, never a burst of stale scans.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import socket
import time
from collections import Counter
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from appliance.sim.scanner_errors import LMS111_NOISE_SIGMA_M, ScannerErrors, statistical_only
from appliance.sim.scanner_model import LMS111_MAX_RANGE_M, RayCache, render_scan
from appliance.sim.site import Site
from drivers.geometry import Pose2D
from drivers.lms111.cola import CommandType, Reply
from drivers.lms111.connection import Lms111Connection
from drivers.lms111.errors import ProtocolError, TruncatedTelegram
from drivers.lms111.framing import NEED_DATA, Dialect
from drivers.lms111.replies import ScanConfig
from drivers.lms111.twin_device import (
    INVALID_COLA_A_CHARACTER,
    INVALID_DATA,
    UNKNOWN_COMMAND,
    DeviceModel,
    PeerState,
)

MAX_CATCH_UP_SCANS: Final = 5
MAX_UNSENT_BYTES: Final = 1 << 20  # a client that stops reading loses scans beyond this
_GARBAGE_ALPHABET: Final = bytes(b for b in range(256) if b != 0x02)  # no start marker

PoseSource = Callable[[float], Pose2D]


@dataclass
class TwinFaults:
    """What to break; every field may be changed while the twin runs."""

    stall: bool = False  # send nothing (answers or scans) to anybody; sockets stay open
    fragment: bool = False  # split every write into random pieces, sent separately
    batch_telegrams: int = 1  # send scans n at a time (several telegrams in one read)
    garbage: bool = False  # random bytes (never a start marker) before every telegram
    corrupt_every: int = 0  # every n-th scan: bad checksum (CoLa-B) / truncated (CoLa-A)
    fail_commands: dict[str, int] = field(default_factory=dict)  # name -> sFA code
    refuse_login: bool = False  # sAN SetAccessMode 0
    boot_s: float = 0.0  # after start(): booting this long
    boot_silent: bool = False  # booting = TCP refused (False) or accepted and silent (True)
    not_ready_s: float = 0.0  # after start(): STlms reports "in preparation" this long


@dataclass
class TwinStats:
    connections: int = 0
    requests: Counter[str] = field(default_factory=Counter)  # by command name
    scans_measured: int = 0
    telegrams_sent: int = 0
    scans_skipped: int = 0  # behind schedule, or the client is not reading
    corrupted: int = 0
    garbage_bytes: int = 0
    writes: int = 0
    truncated_requests: int = 0  # CoLa-A frames cut off by an STX: dropped, never answered


@dataclass(eq=False)
class _Peer:
    writer: asyncio.StreamWriter
    connection: Lms111Connection
    state: PeerState = field(default_factory=PeerState)
    stalled: bool = False
    pending: list[bytes] = field(default_factory=list)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)


class Lms111Twin:
    """One simulated LMS111 on ``host:port`` (port 0: a free one, see `port` after start)."""

    def __init__(
        self,
        site: Site,
        mount: Pose2D,
        pose_source: PoseSource,
        *,
        name: str = "lms111",
        serial_number: int = 0x0142_0001,
        errors: ScannerErrors | None = None,
        range_bias_m: float | None = None,
        seed: int = 0,
        host: str = "127.0.0.1",
        port: int = 0,
        clock: Callable[[], float] = time.monotonic,
        dialect: Dialect = Dialect.COLA_A,
        scan_frequency_hz: float = 50.0,
        angular_resolution_deg: float = 0.5,
        noise_sigma_m: float | None = None,
        max_range_m: float = LMS111_MAX_RANGE_M,
        device_time_offset_us: int = 0,
        faults: TwinFaults | None = None,
    ) -> None:
        self.site = site
        self.mount = mount
        self.pose_source = pose_source
        self.name = name
        self.host = host
        # ``errors``: what the scanner gets wrong (`draw_scanner_errors`; by default a
        # typical LMS111 on its configured mount). ``range_bias_m``/``noise_sigma_m``
        # instead: the older thin-ray model of a fixed offset and white noise only.
        legacy = range_bias_m is not None or noise_sigma_m is not None
        if errors is not None and legacy:
            raise ValueError("give either errors or range_bias_m/noise_sigma_m, not both")
        if errors is None:
            sigma_m = LMS111_NOISE_SIGMA_M if noise_sigma_m is None else noise_sigma_m
            errors = statistical_only(range_bias_m or 0.0, sigma_m) if legacy else ScannerErrors()
        self.errors = errors
        self.max_range_m = max_range_m
        self.faults = faults or TwinFaults()
        self.stats = TwinStats()
        self._port = port
        self._clock = clock
        self._initial_dialect = dialect
        self._rng = np.random.default_rng(seed)
        self._ray_cache = RayCache()  # the vehicle at rest sees the same site
        self._fault_rng = random.Random(seed)
        self.device = DeviceModel(
            self._render,
            serial_number=serial_number,
            location_name=name,
            dialect=dialect,
            config=ScanConfig.from_si(scan_frequency_hz, angular_resolution_deg),
            device_time_offset_us=device_time_offset_us,
        )
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[Any]] = set()  # the stream loop and the boot timer
        self._handlers: set[asyncio.Task[Any]] = set()  # one per connection
        self._peers: set[_Peer] = set()
        self._boot_until_s = 0.0
        self._run_streams = False  # `run` streams itself, even while powered off

    # ---- lifecycle ------------------------------------------------------------------
    @property
    def port(self) -> int:
        """The bound TCP port (fixed at the first start, reused by every restart)."""
        return self._port

    @property
    def running(self) -> bool:
        return self._server is not None

    async def start(self) -> None:
        """Power up: listen (after the boot delay, if any) and stream in a task of our own."""
        await self._power_up()
        self._own(self._stream_loop(None), "stream")

    async def run(self, beat: Callable[[], None]) -> None:
        """The daemon's service: serve until cancelled, beating once per scan period."""
        await self._power_up()
        self._run_streams = True
        try:
            await self._stream_loop(beat)
        finally:
            self._run_streams = False
            await self.stop()

    async def power_on(self) -> None:
        """Power up again after :meth:`stop` (a no-op while running): the boot starts over."""
        if self._server is not None:
            return
        await self._power_up()
        if not self._run_streams:
            self._own(self._stream_loop(None), "stream")

    async def stop(self) -> None:
        """Power off: close the listener and every connection, join our tasks.

        Connection handlers are not cancelled but left to see their reset and return
        (Python 3.11's stream server logs a cancelled handler as an error).
        """
        server, self._server = self._server, None
        if server is not None:
            server.close()
        for peer in list(self._peers):
            peer.writer.transport.abort()
        current = asyncio.current_task()
        own = [task for task in self._tasks if task is not current]
        for task in own:
            task.cancel()
        await asyncio.gather(*own, return_exceptions=True)
        handlers = [task for task in self._handlers if task is not current]
        if handlers:
            _, late = await asyncio.wait(handlers, timeout=1.0)
            for task in late:
                task.cancel()
        if server is not None:
            await server.wait_closed()

    async def _power_up(self) -> None:
        if self._server is not None:
            raise RuntimeError(f"twin {self.name!r} is already running")
        now_s = self._clock()
        faults = self.faults
        self.device.dialect = self._initial_dialect
        self.device.boot(now_s, not_ready_s=faults.boot_s + faults.not_ready_s)
        self._boot_until_s = now_s + faults.boot_s
        self._server = await asyncio.start_server(
            self._serve, self.host, self._port, start_serving=False, reuse_address=True
        )
        self._port = self._server.sockets[0].getsockname()[1]
        if faults.boot_s > 0 and not faults.boot_silent:  # bound but not listening: refused
            self._own(self._listen_after(faults.boot_s), "boot")
        else:
            await self._server.start_serving()

    async def _listen_after(self, delay_s: float) -> None:
        await asyncio.sleep(delay_s)
        if self._server is not None:
            await self._server.start_serving()

    def _own(self, coroutine: Coroutine[Any, Any, None], label: str) -> None:
        """Tasks the twin starts itself (tests, benchmarks); `stop` cancels and joins them."""
        task = asyncio.create_task(coroutine, name=f"lms111-twin:{self.name}:{label}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ---- faults that act at once --------------------------------------------------------
    def drop_connections(self) -> None:
        """Reset every open connection (what a reboot or a pulled cable looks like)."""
        for peer in list(self._peers):
            peer.writer.transport.abort()

    def stall_connections(self) -> None:
        """Open connections go silent for good; new ones work (a half-open TCP session)."""
        for peer in self._peers:
            peer.stalled = True

    def report_not_ready(self, seconds: float) -> None:
        """``STlms`` says "in preparation" and no scans flow for ``seconds`` from now."""
        self.device.not_ready_until_s = self._clock() + seconds

    # ---- serving --------------------------------------------------------------------
    def _booting(self, now_s: float) -> bool:
        return now_s < self._boot_until_s

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._handlers.add(task)
            task.add_done_callback(self._handlers.discard)
        sock = writer.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        peer = _Peer(writer, Lms111Connection(self.device.dialect))
        self._peers.add(peer)
        self.stats.connections += 1
        try:
            while data := await reader.read(65536):
                if self._booting(self._clock()):
                    continue  # silent boot: the stack accepts, the application is not up
                peer.connection.receive_data(data)
                await self._answer_all(peer)
        except (ConnectionError, OSError):
            pass
        finally:
            self._peers.discard(peer)
            writer.transport.abort()

    async def _answer_all(self, peer: _Peer) -> None:
        connection = peer.connection
        while True:
            try:
                event = connection.next_event()
            except TruncatedTelegram:  # e.g. a CoLa-B probe: a CoLa-A LMS1xx stays silent
                self.stats.truncated_requests += 1
                continue
            except ProtocolError:
                bad = INVALID_COLA_A_CHARACTER if connection.dialect is Dialect.COLA_A else 0
                await self._send(peer, connection.send_error(bad or INVALID_DATA))
                continue
            if event is NEED_DATA:
                return
            if not isinstance(event, Reply):  # a scan or an sFA sent *to* a scanner
                await self._send(peer, connection.send_error(UNKNOWN_COMMAND))
                continue
            self.stats.requests[event.name] += 1
            self.device.refuse_login = self.faults.refuse_login
            self.device.fail_commands = self.faults.fail_commands
            answer = self.device.handle(event, peer.state, self._clock())
            if answer.error_code is not None:
                data = connection.send_error(answer.error_code)
            elif answer.scan is not None:
                data = connection.send_scan(answer.scan, CommandType.SRA)
            else:
                assert answer.command is not None
                data = connection.send(answer.command)
            await self._send(peer, data)
            if answer.switch_to is not None:
                self.device.dialect = answer.switch_to
                for other in self._peers:
                    other.connection.switch_dialect(answer.switch_to)

    async def _send(self, peer: _Peer, data: bytes, *, scan: bool = False) -> None:
        faults = self.faults
        transport = peer.writer.transport
        if faults.stall or peer.stalled or transport.is_closing():
            return
        if scan and transport.get_write_buffer_size() > MAX_UNSENT_BYTES:
            self.stats.scans_skipped += 1
            return
        every = faults.corrupt_every
        if scan and every > 0 and (self.stats.telegrams_sent + 1) % every == 0:
            data = self._corrupt(data, peer.connection.dialect)
        if faults.garbage:
            length = self._fault_rng.randint(1, 24)
            noise = bytes(self._fault_rng.choices(_GARBAGE_ALPHABET, k=length))
            self.stats.garbage_bytes += length
            data = noise + data
        if scan and faults.batch_telegrams > 1:
            peer.pending.append(data)
            if len(peer.pending) < faults.batch_telegrams:
                return
        if peer.pending:
            data = b"".join(peer.pending) + (b"" if scan else data)
            peer.pending.clear()
        async with peer.lock:  # fragments of one write must not interleave with another
            if not faults.fragment:
                self._write(peer, data)
                return
            start = 0
            while start < len(data):
                end = min(len(data), start + self._fault_rng.randint(1, 1500))
                self._write(peer, data[start:end])
                start = end
                await asyncio.sleep(0)  # let the reader see this piece on its own

    def _write(self, peer: _Peer, data: bytes) -> None:
        if not peer.writer.transport.is_closing():
            peer.writer.write(data)
            self.stats.writes += 1

    def _corrupt(self, data: bytes, dialect: Dialect) -> bytes:
        self.stats.corrupted += 1
        if dialect is Dialect.COLA_B:
            return data[:-1] + bytes([data[-1] ^ 0x5A])  # checksum no longer matches
        return data[: len(data) // 2]  # no ETX: the next STX exposes the truncation

    # ---- scans ----------------------------------------------------------------------
    @property
    def true_mount(self) -> Pose2D:
        """Where the scanner really sits on the vehicle (``mount`` is the configured one)."""
        return self.errors.true_mount(self.mount)

    def _render(
        self, t_s: float, angles_rad: npt.NDArray[np.float64]
    ) -> tuple[npt.NDArray[np.float64], ...]:
        step = float(angles_rad[1] - angles_rad[0]) if len(angles_rad) > 1 else 1e-3
        ranges, remission = render_scan(
            self.site,
            t_s,
            self.pose_source(t_s),
            self.mount,
            rng=self._rng,
            start_angle_rad=float(angles_rad[0]),
            stop_angle_rad=float(angles_rad[-1]),
            step_rad=step,
            errors=self.errors,
            max_range_m=self.max_range_m,
            cache=self._ray_cache,
        )
        count = len(angles_rad)  # float rounding must never change the beam count
        if len(ranges) != count:
            ranges = np.resize(ranges, count)
            remission = np.resize(remission, count)
        return ranges, remission

    async def _stream_loop(self, beat: Callable[[], None] | None) -> None:
        """One scan per period on an absolute schedule (no drift, no bursts)."""
        next_s = self._clock()
        while True:
            period_s = self.device.period_s
            now_s = self._clock()
            if now_s < next_s:
                await asyncio.sleep(next_s - now_s)
                continue
            behind = int((now_s - next_s) / period_s)
            if behind > MAX_CATCH_UP_SCANS:
                if self.device.streaming(now_s) and not self._booting(now_s):
                    self.device.skip(behind)
                    self.stats.scans_skipped += behind
                next_s += behind * period_s
            await self._emit(next_s)
            next_s += period_s
            if beat is not None:
                beat()

    async def _emit(self, t_s: float) -> None:
        if self._server is None or self._booting(t_s) or not self.device.streaming(t_s):
            return
        subscribers = [p for p in self._peers if "LMDscandata" in p.state.subscriptions]
        scan = self.device.measure(t_s, render=bool(subscribers))
        self.stats.scans_measured += 1
        if scan is None:
            return
        for peer in subscribers:
            telegram = self.device.telegram(scan)
            await self._send(peer, peer.connection.send_scan(telegram), scan=True)
            self.stats.telegrams_sent += 1
