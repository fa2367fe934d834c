"""What the driver says to an LMS111 before the scans flow, and `probe` for the CLI.

The start-up sequence, in the order proven by clearpath ``LMS1xx`` (login, configure,
``LMCstartmeas``, wait for ``STlms`` = 7, ``Run``, subscribe) with one extra status check
before configuring, so a scanner that is still initialising is waited for instead of
being configured half-way (clearpath LMS1xx #11: the driver "catches the sensor in an
inconsistent boot-up state" and hangs):

1. ``sMN SetAccessMode 03 F4724744`` — authorised client; ``sAN SetAccessMode 0`` is fatal.
2. ``sRN STlms`` until the device is up: idle (3), ready (6) or measuring (7). Any other
   state (initialisation, in preparation ...) is "not ready": poll again, log once.
3. ``sMN mLMPsetscancfg`` — frequency, resolution, -45°..225°. The answer carries a status
   (0 ok) and the values applied; anything else is fatal with the status's meaning.
4. ``sWN LMDscandatacfg`` — echo 1, 16-bit remission on, every scan.
5. ``sMN LMCstartmeas`` — answer 0 = accepted; then ``STlms`` until 7 (measuring).
6. ``sMN Run`` — log out and apply (answer 1), then ``sEN LMDscandata 1``.

Any ``sFA`` on the way is fatal (`Lms111ConfigError` naming the command), except "server
busy", which is retried like a link failure.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Final, TypeVar

from drivers.lms111.cola import Command, Reply
from drivers.lms111.commands import (
    ScanDataConfig,
    configure_scan_data,
    read_device_ident,
    read_device_state,
    read_device_status,
    read_firmware_version,
    read_location_name,
    read_output_range,
    read_scan_config,
    run,
    set_access_mode,
    set_scan_config,
    start_measurement,
    subscribe_scans,
)
from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import Dialect
from drivers.lms111.replies import (
    DeviceIdent,
    DeviceStatus,
    LmsState,
    ScanConfig,
    parse_access_mode,
    parse_device_ident,
    parse_device_state,
    parse_device_status,
    parse_event_answer,
    parse_method_status,
    parse_output_range,
    parse_scan_config,
    parse_set_scan_config,
    parse_string_variable,
)
from drivers.lms111.session import (
    Lms111ConfigError,
    Lms111LoginError,
    Lms111Session,
    SopasRefused,
    refusal_to_config_error,
)

T = TypeVar("T")

UP_STATES: Final = frozenset({LmsState.IDLE, LmsState.READY, LmsState.MEASURING})
START_MEASUREMENT_OK: Final = 0
RUN_OK: Final = 1


@dataclass(frozen=True)
class StreamSettings:
    """What to ask the scanner for (from `Lms111Endpoint`)."""

    scan_frequency_hz: float = 50.0
    angular_resolution_deg: float = 0.5
    start_angle_deg: float = -45.0
    stop_angle_deg: float = 225.0
    data: ScanDataConfig = field(default_factory=ScanDataConfig)

    @property
    def scan_config(self) -> ScanConfig:
        return ScanConfig.from_si(
            self.scan_frequency_hz,
            self.angular_resolution_deg,
            self.start_angle_deg,
            self.stop_angle_deg,
        )


NotReadyHook = Callable[[DeviceStatus], None]


async def _checked(what: str, step: Awaitable[T], scanner: str) -> T:
    """Run one request step, turning refusals and undecodable answers into clear errors."""
    try:
        return await step
    except SopasRefused as exc:
        raise refusal_to_config_error(exc, scanner) from exc
    except ProtocolError as exc:  # an answer we cannot read: is this an LMS111 at all?
        raise Lms111ConfigError(what, None, f"unexpected answer: {exc}", scanner) from exc


async def _ask(session: Lms111Session, command: Command, parse: Callable[[Reply], T]) -> T:
    return parse(await session.request(command))


async def read_status(session: Lms111Session, scanner: str = "") -> DeviceStatus:
    return await _checked(
        "STlms", _ask(session, read_device_status(), parse_device_status), scanner
    )


async def wait_until(
    session: Lms111Session,
    accept: frozenset[int],
    *,
    poll_s: float,
    on_not_ready: NotReadyHook,
    scanner: str = "",
) -> DeviceStatus:
    """Poll ``STlms`` until its state is in ``accept``; report each other answer."""
    while True:
        status = await read_status(session, scanner)
        if status.state in accept:
            return status
        on_not_ready(status)
        await asyncio.sleep(poll_s)


async def start_streaming(
    session: Lms111Session,
    settings: StreamSettings,
    *,
    ready_poll_s: float = 1.0,
    on_not_ready: NotReadyHook = lambda status: None,
    scanner: str = "",
) -> ScanConfig:
    """Log in, wait until up, configure, start, subscribe; the configuration applied."""
    await login(session, scanner)
    await wait_until(
        session, UP_STATES, poll_s=ready_poll_s, on_not_ready=on_not_ready, scanner=scanner
    )
    applied = await _checked(
        "mLMPsetscancfg",
        _ask(session, set_scan_config(settings.scan_config), parse_set_scan_config),
        scanner,
    )
    if not applied.ok:
        raise Lms111ConfigError(
            "mLMPsetscancfg",
            applied.status,
            f"{applied.meaning} (asked for {settings.scan_frequency_hz:g} Hz, "
            f"{settings.angular_resolution_deg:g}°, {settings.start_angle_deg:g}°.."
            f"{settings.stop_angle_deg:g}°)",
            scanner,
        )
    await _checked("LMDscandatacfg", session.request(configure_scan_data(settings.data)), scanner)
    await _method(session, start_measurement(), START_MEASUREMENT_OK, scanner)
    await wait_until(
        session,
        frozenset({LmsState.MEASURING}),
        poll_s=ready_poll_s,
        on_not_ready=on_not_ready,
        scanner=scanner,
    )
    await _method(session, run(), RUN_OK, scanner)
    subscribed = await _checked(
        "LMDscandata", _ask(session, subscribe_scans(), parse_event_answer), scanner
    )
    if not subscribed:
        raise Lms111ConfigError("LMDscandata", None, "subscription not confirmed", scanner)
    return applied.config


async def login(session: Lms111Session, scanner: str = "") -> None:
    """``SetAccessMode`` as authorised client; refused (or sFA) is `Lms111LoginError`."""
    try:
        granted = await _checked(
            "SetAccessMode", _ask(session, set_access_mode(), parse_access_mode), scanner
        )
    except Lms111ConfigError as exc:
        raise Lms111LoginError("SetAccessMode", exc.code, exc.meaning, scanner) from exc
    if not granted:
        raise Lms111LoginError(
            "SetAccessMode",
            None,
            "login as authorised client (level 3) was refused: wrong password or level",
            scanner,
        )


async def _method(session: Lms111Session, command: Command, ok: int, scanner: str) -> None:
    """A method whose answer is one status value (``sAN LMCstartmeas 0``, ``sAN Run 1``)."""
    status = await _checked(
        command.name,
        _ask(session, command, lambda reply: parse_method_status(reply, command.name)),
        scanner,
    )
    if status != ok:
        raise Lms111ConfigError(command.name, status, f"answered status {status}", scanner)


@dataclass(frozen=True)
class ProbeResult:
    """What ``dbw lms111 probe HOST:PORT`` prints; None where the scanner refused."""

    host: str
    port: int
    dialect: str
    device_ident: DeviceIdent | None = None
    firmware_version: str | None = None
    location_name: str | None = None
    device_state: int | None = None
    status: DeviceStatus | None = None
    scan_config: ScanConfig | None = None
    output_range: ScanConfig | None = None
    errors: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (``json.dumps(result.to_dict())``), angles and rates in SI too."""
        data = asdict(self)
        for key in ("scan_config", "output_range"):
            config: ScanConfig | None = getattr(self, key)
            if config is not None:
                data[key].update(
                    scan_frequency_hz=config.scan_frequency_hz,
                    angular_resolution_deg=config.angular_resolution_deg,
                    start_angle_deg=config.start_angle_deg,
                    stop_angle_deg=config.stop_angle_deg,
                )
        if self.status is not None:
            data["status"]["measuring"] = self.status.measuring
        return data


async def probe(
    host: str, port: int, timeout_s: float = 2.0, dialect: Dialect = Dialect.COLA_A
) -> ProbeResult:
    """Connect, read identity, status and configuration without changing anything.

    A link failure raises `Lms111LinkError`; an item the scanner refuses or answers in a
    shape we cannot read is left None and explained in ``errors`` (older firmware does not
    know every variable), so one missing answer does not hide the others.
    """
    session = await Lms111Session.connect(
        host, port, dialect, connect_timeout_s=timeout_s, request_timeout_s=timeout_s
    )
    values: dict[str, Any] = {}
    errors: dict[str, str] = {}
    items: tuple[tuple[str, Command, Callable[[Reply], Any]], ...] = (
        ("device_ident", read_device_ident(), parse_device_ident),
        (
            "firmware_version",
            read_firmware_version(),
            lambda reply: parse_string_variable(reply, "FirmwareVersion"),
        ),
        (
            "location_name",
            read_location_name(),
            lambda reply: parse_string_variable(reply, "LocationName"),
        ),
        ("device_state", read_device_state(), parse_device_state),
        ("status", read_device_status(), parse_device_status),
        ("scan_config", read_scan_config(), parse_scan_config),
        ("output_range", read_output_range(), parse_output_range),
    )
    try:
        for key, command, parse in items:
            try:
                values[key] = await _ask(session, command, parse)
            except SopasRefused as exc:
                errors[key] = f"sFA {exc.error.code:X}: {exc.error.meaning}"
            except ProtocolError as exc:
                errors[key] = f"unreadable answer: {exc}"
    finally:
        await session.close()
    return ProbeResult(host, port, dialect.value, **values, errors=errors)
