"""One LMS111 TCP stream as a sans-I/O object: framing + typing, both directions.

The asyncio client is a read-feed-drain loop::

    conn = Lms111Connection()
    writer.write(conn.send(subscribe_scans()))
    while data := await reader.read(65536):
        conn.receive_data(data)
        while True:
            try:
                event = conn.next_event(host_receive_time_s=clock())
            except ProtocolError as exc:   # the bad telegram is already dropped
                log.warning("lms111 telegram dropped", error=str(exc))
                continue
            if event is NEED_DATA:
                break
            handle(event)

The twin uses the same object the other way round: it receives requests (as `Reply`
events) and answers with `send(...)`, `send_scan(...)` and `send_error(...)`.

Switching dialect is explicit: after ``sWA EIHstCola`` (or, on the twin, after sending it)
call `switch_dialect`; the answer itself still comes in the old dialect.
"""

from __future__ import annotations

from drivers.lms111.cola import (
    Command,
    CommandType,
    Event,
    encode_error,
    encode_scan_telegram,
    parse_telegram,
)
from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import (
    DEFAULT_MAX_BUFFER_BYTES,
    DEFAULT_MAX_TELEGRAM_BYTES,
    NEED_DATA,
    ColaFramer,
    Dialect,
    NeedData,
)
from drivers.lms111.scan import Scan


class Lms111Connection:
    def __init__(
        self,
        dialect: Dialect = Dialect.COLA_A,
        *,
        max_telegram_bytes: int = DEFAULT_MAX_TELEGRAM_BYTES,
        max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES,
    ) -> None:
        self._framer = ColaFramer(
            dialect, max_telegram_bytes=max_telegram_bytes, max_buffer_bytes=max_buffer_bytes
        )
        self._undecodable = 0

    @property
    def dialect(self) -> Dialect:
        return self._framer.dialect

    @property
    def garbage_bytes(self) -> int:
        return self._framer.garbage_bytes

    @property
    def malformed_telegrams(self) -> int:
        """Telegrams dropped by the framer plus framed ones that did not parse."""
        return self._framer.malformed_telegrams + self._undecodable

    def reset(self) -> None:
        self._framer.reset()
        self._undecodable = 0

    def switch_dialect(self, dialect: Dialect) -> None:
        self._framer.switch_dialect(dialect)

    def receive_data(self, data: bytes) -> None:
        self._framer.receive_data(data)

    def next_event(self, *, host_receive_time_s: float | None = None) -> Event | NeedData:
        """The next typed event or `NEED_DATA`; `ProtocolError` after dropping a bad one."""
        telegram = self._framer.next_event()
        if telegram is NEED_DATA:
            return NEED_DATA
        try:
            return parse_telegram(telegram, host_receive_time_s=host_receive_time_s)
        except ProtocolError:
            self._undecodable += 1
            raise

    def send(self, command: Command) -> bytes:
        return command.encode(self.dialect)

    def send_scan(self, scan: Scan, kind: CommandType = CommandType.SSN) -> bytes:
        return encode_scan_telegram(scan, self.dialect, kind)

    def send_error(self, code: int) -> bytes:
        return encode_error(code, self.dialect)
