"""The simulated LMS111's behaviour, without sockets: requests in, answers out, scans made.

`DeviceModel` is what the twin's TCP server wraps. It holds what a real LMS111 holds (scan
configuration, scan data content, measuring or not, user level per connection, counters,
a microsecond clock since power-up) and answers every request the official drivers send at
start-up (clearpath ``LMS1xx``, SICK ``sick_scan_xd``) with the replies a real device gives:

* reads: ``DeviceIdent``, ``FirmwareVersion``, ``SerialNumber``, ``LocationName``,
  ``SCdevicestate``, ``STlms``, ``LMPscancfg``, ``LMPoutputRange``, ``LMDscandatacfg``,
  ``ODoprh``, ``ODpwrc``, ``LFErec``, ``LIDoutputstate``, ``LIDinputstate``, ``field000``
  .. ``field029`` (empty fields, see `twin_fields`), and ``LMDscandata`` (one scan, ``sRA``);
* writes (logged in): ``LMDscandatacfg``, ``LMPoutputRange``, ``EIHstCola`` (the answer
  goes out in the old dialect, then the device switches);
* methods: ``SetAccessMode`` (level 3 ``F4724744``, level 2 ``B21ACE26``), and, logged
  in, ``mLMPsetscancfg``, ``LMCstartmeas``, ``LMCstopmeas``, ``mEEwriteall``; ``Run``;
* events: ``sEN LMDscandata`` / ``LFErec`` / ``LIDoutputstate`` / ``LIDinputstate``.

Refusals use the SOPAS codes a device sends: unknown variable 3, unknown method 2, unknown
event F, write without login A, method without login 1, missing parameters 8 (what an
LMS1xx answered to a short ``mLMPsetscancfg``, sick_scan_xd #39), other bad parameters 5;
first of all, 11 to CoLa-A parameters that are not printable ASCII (an LMS1xx V1.80.1 did
so to binary ``mLMPsetscancfg`` values in a CoLa-A frame, sick_scan_xd #128).
``mLMPsetscancfg`` accepts 25 Hz at 0.25° or 0.5° and 50 Hz at 0.5° (36 kHz measurement
rate at most); 50 Hz at 0.25° gets status 2 (resolution error), as on the device.
One quirk is reproduced on purpose: ``LMPoutputRange`` always reports 0.5° whatever the
resolution (clearpath LMS1xx #39 and #51), so a driver must take the resolution from the
scan configuration or the scan itself.
"""

from __future__ import annotations

import copy
import datetime as dt
import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Final

import numpy as np
import numpy.typing as npt

from drivers.lms111 import twin_fields
from drivers.lms111.cola import Command, CommandType, Reply
from drivers.lms111.commands import (
    AUTHORIZED_CLIENT,
    AUTHORIZED_CLIENT_PASSWORD,
    MAINTENANCE,
    MAINTENANCE_PASSWORD,
    ScanDataConfig,
    configure_scan_data,
    parse_event_request,
    parse_scan_data_config_request,
    parse_set_access_mode_request,
    parse_set_dialect_request,
    parse_set_scan_config_request,
)
from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import Dialect
from drivers.lms111.replies import (
    DeviceIdent,
    DeviceState,
    DeviceStatus,
    LmsState,
    ScanConfig,
    answer_access_mode,
    answer_device_ident,
    answer_device_state,
    answer_device_status,
    answer_event,
    answer_method,
    answer_output_range,
    answer_scan_config,
    answer_set_scan_config,
    answer_string_variable,
    answer_write,
    read_scan_sectors,
)
from drivers.lms111.scan import Channel, Scan, ScanTimestamp
from drivers.lms111.values import FLEXSTR, U16, U32, FieldType, Value

WRAP_US: Final = 1 << 32
SUPPORTED_MODES: Final = frozenset({(2500, 2500), (2500, 5000), (5000, 5000)})
LMS111_MIN_ANGLE: Final = -450_000
LMS111_MAX_ANGLE: Final = 2_250_000
EPOCH: Final = dt.datetime(1970, 1, 1)  # the device clock's date without NTP ("01.01.1970")
EVENTS: Final = frozenset({"LMDscandata", "LFErec", "LIDoutputstate", "LIDinputstate"})
PASSWORDS: Final = {
    AUTHORIZED_CLIENT: AUTHORIZED_CLIENT_PASSWORD,
    MAINTENANCE: MAINTENANCE_PASSWORD,
}

# SOPAS error codes the device answers with (see cola.SOPAS_ERRORS).
ACCESS_DENIED: Final = 0x01
UNKNOWN_METHOD: Final = 0x02
UNKNOWN_VARIABLE: Final = 0x03
INVALID_DATA: Final = 0x05
BUFFER_UNDERFLOW: Final = 0x08
WRITE_ACCESS_DENIED: Final = 0x0A
UNKNOWN_COMMAND: Final = 0x0C
UNKNOWN_EVENT: Final = 0x0F
INVALID_COLA_A_CHARACTER: Final = 0x11
_COLA_A_TEXT: Final = re.compile(rb"[\x20-\x7e]*")  # what CoLa-A parameters may hold

# What one scan measures: ranges (m, 0 = no echo) and remission, given the time, the
# device angles (rad) of the beams, and the configured angles.
RangeSource = Callable[[float, npt.NDArray[np.float64]], tuple[npt.NDArray[np.float64], ...]]


def rssi_digits(
    remission: npt.NDArray[np.float64], ranges_m: npt.NDArray[np.float64], bits16: bool
) -> npt.NDArray[np.float64]:
    """A plausible RSSI: brighter surfaces and nearer ones give more signal.

    Not the device's calibration (SICK does not publish one): proportional to remission
    (white paper ~0.9 gives ~900 digits at 1 m in 16-bit mode), falling with the square root
    of the range, saturating for retro-reflectors; 8-bit mode is the same scaled to 0..255.
    No echo, no signal.
    """
    digits = 1000.0 * remission / np.sqrt(np.maximum(ranges_m, 1.0))
    top = 65535.0 if bits16 else 255.0
    if not bits16:
        digits *= 255.0 / 1000.0
    return np.where(ranges_m > 0.0, np.clip(np.rint(digits), 0.0, top), 0.0)


@dataclass
class PeerState:
    """What the device keeps per TCP connection: user level and subscriptions."""

    access_level: int = 0
    subscriptions: set[str] = field(default_factory=set)


@dataclass(frozen=True)
class Answer:
    """The device's reaction to one request: a telegram or an ``sFA`` code, plus effects."""

    command: Command | None = None
    error_code: int | None = None
    switch_to: Dialect | None = None  # after sending the answer (EIHstCola)
    scan: Scan | None = None  # sRA LMDscandata


class DeviceModel:
    """One LMS111; every method takes the time, nothing reads a clock.

    ``ranges(t_s, device_angles_rad)`` is the world: it returns the ranges (m, 0 = no
    echo) and remission the scanner measures along those beams at ``t_s``.
    """

    def __init__(
        self,
        ranges: RangeSource,
        *,
        serial_number: int = 0x0142_0001,
        device_ident: DeviceIdent | None = None,
        firmware_version: str = "V1.80",
        location_name: str = "not defined",
        dialect: Dialect = Dialect.COLA_A,
        config: ScanConfig | None = None,
        data_config: ScanDataConfig | None = None,
        device_time_offset_us: int = 0,
    ) -> None:
        self.ranges = ranges
        self.serial_number = serial_number
        self.device_ident = device_ident or DeviceIdent("LMS11x_FieldEval", "V1.80-15.11.2016")
        self.firmware_version = firmware_version
        self.location_name = location_name
        self.dialect = dialect
        self.config = config or ScanConfig(5000, 5000)
        self.data_config = data_config or ScanDataConfig()
        self.device_time_offset_us = device_time_offset_us
        self.refuse_login = False
        self.fail_commands: dict[str, int] = {}
        self.output_start = self.config.start_angle_10000th_deg
        self.output_stop = self.config.stop_angle_10000th_deg
        self.power_on_count = 0
        self._angles_key: tuple[int, int, int] | None = None
        self._angles = (np.zeros(0, dtype=np.int64), np.zeros(0))
        self.boot(0.0)

    # ---- power and clocks ---------------------------------------------------------
    def boot(self, now_s: float, not_ready_s: float = 0.0) -> None:
        """Power-up: the clock restarts at the offset, counters at 0, measuring on."""
        self.booted_at_s = now_s
        self.not_ready_until_s = now_s + not_ready_s
        self.measuring = True
        self.scan_counter = 0
        self.telegram_counter = 0
        self.power_on_count += 1
        self.latest_scan: Scan | None = None

    def device_time_us(self, now_s: float) -> int:
        return (self.device_time_offset_us + round((now_s - self.booted_at_s) * 1e6)) % WRAP_US

    def ready(self, now_s: float) -> bool:
        return now_s >= self.not_ready_until_s

    def streaming(self, now_s: float) -> bool:
        """Measuring, ready, and one full sweep since power-up: scans exist."""
        return self.measuring and self.ready(now_s) and now_s - self.booted_at_s >= self.period_s

    @property
    def period_s(self) -> float:
        return 100.0 / self.config.scan_frequency_100th_hz

    def status(self, now_s: float) -> DeviceStatus:
        if not self.ready(now_s):
            state = LmsState.IN_PREPARATION
        else:
            state = LmsState.MEASURING if self.measuring else LmsState.IDLE
        uptime_s = int(now_s - self.booted_at_s)
        clock_text = f"{uptime_s // 3600 % 24:02d}:{uptime_s // 60 % 60:02d}:{uptime_s % 60:02d}"
        return DeviceStatus(int(state), False, clock_text, "01.01.1970")

    # ---- scans --------------------------------------------------------------------
    def beam_angles_10000th_deg(self) -> npt.NDArray[np.int64]:
        step = self.config.angular_resolution_10000th_deg
        start, stop = self.output_start, self.output_stop
        count = (stop - start) // step + 1
        return start + step * np.arange(count, dtype=np.int64)

    def measure(self, now_s: float, *, render: bool = True) -> Scan | None:
        """One scan period ends at ``now_s``: count it, and build it if anybody wants it."""
        self.scan_counter = (self.scan_counter + 1) & 0xFFFF
        if not render:
            return None
        scan = self._build(now_s)
        self.latest_scan = scan
        return scan

    def skip(self, scans: int) -> None:
        """Scans measured but never sent (the twin fell behind): the counter still moves."""
        self.scan_counter = (self.scan_counter + scans) & 0xFFFF

    def telegram(self, scan: Scan) -> Scan:
        """The scan as the next telegram (each telegram sent advances the counter).

        A shallow copy with the counter set: `dataclasses.replace` would run the frozen
        22-field ``__init__`` again, which cost more than encoding a CoLa-B scan's data.
        """
        self.telegram_counter = (self.telegram_counter + 1) & 0xFFFF
        telegram = copy.copy(scan)
        object.__setattr__(telegram, "telegram_counter", self.telegram_counter)
        return telegram

    def _beam_angles(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        """`beam_angles_10000th_deg` and in radians, kept until the configuration changes."""
        key = (self.output_start, self.output_stop, self.config.angular_resolution_10000th_deg)
        if self._angles_key != key:
            angles = self.beam_angles_10000th_deg()
            self._angles = (angles, np.radians(angles * 1e-4))
            self._angles_key = key
        return self._angles

    def _build(self, now_s: float) -> Scan:
        angles, angles_rad = self._beam_angles()
        ranges_m, remission = self.ranges(now_s, angles_rad.copy())[:2]
        start, step = int(angles[0]), self.config.angular_resolution_10000th_deg
        dc = self.data_config
        channels16: list[Channel] = []
        channels8: list[Channel] = []
        for echo in (1, 2):
            if not dc.output_channel & echo:
                continue
            echo_ranges = ranges_m if echo == 1 else np.zeros_like(ranges_m)  # no 2nd echo
            raw = np.clip(np.rint(echo_ranges * 1e3), 0, 0xFFFF).astype(np.uint16)
            channels16.append(Channel(f"DIST{echo}", 1.0, 0.0, start, step, raw))
            if dc.remission:
                rssi = rssi_digits(remission, echo_ranges, dc.remission_16bit)
                dtype = np.uint16 if dc.remission_16bit else np.uint8
                target = channels16 if dc.remission_16bit else channels8
                target.append(Channel(f"RSSI{echo}", 1.0, 0.0, start, step, rssi.astype(dtype)))
        for channel in channels16 + channels8:
            channel.data.flags.writeable = False
        started_s = now_s - self.period_s  # the telegram leaves once the sweep is done
        timestamp = None
        if dc.time:
            t = EPOCH + dt.timedelta(seconds=now_s - self.booted_at_s)
            timestamp = ScanTimestamp(
                t.year, t.month, t.day, t.hour, t.minute, t.second, t.microsecond
            )
        frequency = self.config.scan_frequency_100th_hz
        return Scan(
            channels_16bit=tuple(channels16),
            channels_8bit=tuple(channels8),
            version=1,
            device_number=1,
            serial_number=self.serial_number,
            scan_counter=self.scan_counter,
            device_time_us=self.device_time_us(started_s),
            transmit_time_us=self.device_time_us(now_s),
            scan_frequency_100th_hz=frequency,
            # beams per second in 100 Hz units: 0x168 (36 kHz) at 50 Hz / 0.5°, as sent
            measurement_frequency_100hz=round(
                frequency * 360 / self.config.angular_resolution_10000th_deg
            ),
            device_name=self.location_name if dc.device_name else None,
            timestamp=timestamp,
        )

    # ---- requests -----------------------------------------------------------------
    def handle(self, request: Reply, peer: PeerState, now_s: float) -> Answer:
        """Answer one request; `ProtocolError` in its parameters becomes an ``sFA``."""
        if request.dialect is Dialect.COLA_A and not _COLA_A_TEXT.fullmatch(request.params):
            return Answer(error_code=INVALID_COLA_A_CHARACTER)
        if request.name in self.fail_commands:
            return Answer(error_code=self.fail_commands[request.name])
        try:
            match request.kind:
                case CommandType.SRN:
                    return self._read(request.name, now_s)
                case CommandType.SWN:
                    return self._write(request, peer)
                case CommandType.SMN:
                    return self._method(request, peer, now_s)
                case CommandType.SEN:
                    return self._event(request, peer)
                case _:
                    return Answer(error_code=UNKNOWN_COMMAND)
        except ProtocolError as exc:
            short = "ends" in str(exc)  # ParamReader: "telegram ends before/inside ..."
            return Answer(error_code=BUFFER_UNDERFLOW if short else INVALID_DATA)

    def _read(self, name: str, now_s: float) -> Answer:
        variables: dict[str, Callable[[], Command]] = {
            "DeviceIdent": lambda: answer_device_ident(self.device_ident),
            "FirmwareVersion": lambda: answer_string_variable(name, self.firmware_version),
            "SerialNumber": lambda: answer_string_variable(name, f"{self.serial_number:08d}"),
            "LocationName": lambda: answer_string_variable(name, self.location_name),
            "SCdevicestate": lambda: answer_device_state(
                DeviceState.READY if self.ready(now_s) else DeviceState.BUSY
            ),
            "STlms": lambda: answer_device_status(self.status(now_s)),
            "LMPscancfg": lambda: answer_scan_config(self.config),
            "LMPoutputRange": lambda: answer_output_range(
                ScanConfig(0, 5000, self.output_start, self.output_stop)  # the 0.5° quirk
            ),
            "LMDscandatacfg": lambda: Command(
                CommandType.SRA, name, configure_scan_data(self.data_config).fields
            ),
            "ODoprh": lambda: _values(name, (U32, 12_345)),  # 1/10 h of operation
            "ODpwrc": lambda: _values(name, (U32, self.power_on_count)),
            "LFErec": lambda: _values(name, (U16, 0)),  # no field evaluation configured
            "LIDoutputstate": lambda: twin_fields.answer_output_state(self.device_time_us(now_s)),
            "LIDinputstate": lambda: twin_fields.answer_input_state(self.device_time_us(now_s)),
        }
        if name == "LMDscandata":
            scan = self.latest_scan or self._build(now_s)
            return Answer(scan=self.telegram(scan))
        if (field_number := twin_fields.field_index(name)) is not None:
            return Answer(command=twin_fields.answer_field(field_number))
        if name not in variables:
            return Answer(error_code=UNKNOWN_VARIABLE)
        return Answer(command=variables[name]())

    def _write(self, request: Reply, peer: PeerState) -> Answer:
        name = request.name
        if name not in ("LMDscandatacfg", "LMPoutputRange", "EIHstCola", "LocationName"):
            return Answer(error_code=UNKNOWN_VARIABLE)
        if peer.access_level < MAINTENANCE:
            return Answer(error_code=WRITE_ACCESS_DENIED)
        if name == "LMDscandatacfg":
            self.data_config = parse_scan_data_config_request(request)
        elif name == "LMPoutputRange":
            reader = request.reader()
            output = read_scan_sectors(reader, 0)
            reader.expect_end()
            if not LMS111_MIN_ANGLE <= output.start_angle_10000th_deg < LMS111_MAX_ANGLE:
                return Answer(error_code=INVALID_DATA)
            self.output_start = output.start_angle_10000th_deg
            self.output_stop = min(output.stop_angle_10000th_deg, LMS111_MAX_ANGLE)
        elif name == "EIHstCola":
            return Answer(command=answer_write(name), switch_to=parse_set_dialect_request(request))
        else:
            (text,) = request.decode((FLEXSTR,))
            self.location_name = str(text)
        return Answer(command=answer_write(name))

    def _method(self, request: Reply, peer: PeerState, now_s: float) -> Answer:
        name = request.name
        if name == "SetAccessMode":
            level, password = parse_set_access_mode_request(request)
            granted = not self.refuse_login and PASSWORDS.get(level) == password
            peer.access_level = level if granted else 0
            return Answer(command=answer_access_mode(granted))
        if name == "Run":  # log out; the configuration is already in effect
            peer.access_level = 0
            return Answer(command=answer_method(name, 1))
        if name not in ("mLMPsetscancfg", "LMCstartmeas", "LMCstopmeas", "mEEwriteall"):
            return Answer(error_code=UNKNOWN_METHOD)
        if peer.access_level < MAINTENANCE:
            return Answer(error_code=ACCESS_DENIED)
        if name == "mLMPsetscancfg":
            return Answer(command=self._set_scan_config(parse_set_scan_config_request(request)))
        if name == "LMCstartmeas":
            self.measuring = True
            return Answer(command=answer_method(name, 0))
        if name == "LMCstopmeas":
            self.measuring = False
            return Answer(command=answer_method(name, 0))
        return Answer(command=answer_method(name, 1))  # mEEwriteall

    def _set_scan_config(self, wanted: ScanConfig) -> Command:
        frequency_ok = wanted.scan_frequency_100th_hz in (2500, 5000)
        resolution_ok = wanted.angular_resolution_10000th_deg in (2500, 5000)
        if not frequency_ok or not resolution_ok:
            status = 3 if not (frequency_ok or resolution_ok) else (1 if resolution_ok else 2)
        elif (wanted.scan_frequency_100th_hz, wanted.angular_resolution_10000th_deg) not in (
            SUPPORTED_MODES
        ):
            status = 2  # 50 Hz at 0.25° would be 72 kHz: the resolution is refused
        elif not (
            LMS111_MIN_ANGLE <= wanted.start_angle_10000th_deg < wanted.stop_angle_10000th_deg
            and wanted.stop_angle_10000th_deg <= LMS111_MAX_ANGLE
        ):
            status = 4
        elif wanted.sector_count != 1:
            status = 5
        else:
            status = 0
            self.config = replace(wanted, sector_count=1)
            self.output_start = wanted.start_angle_10000th_deg
            self.output_stop = wanted.stop_angle_10000th_deg
        return answer_set_scan_config(status, self.config)

    def _event(self, request: Reply, peer: PeerState) -> Answer:
        if request.name not in EVENTS:
            return Answer(error_code=UNKNOWN_EVENT)
        enable = parse_event_request(request)
        if enable:
            peer.subscriptions.add(request.name)
        else:
            peer.subscriptions.discard(request.name)
        return Answer(command=answer_event(request.name, enable))


def _values(name: str, *fields: tuple[FieldType, Value]) -> Command:
    return Command(CommandType.SRA, name, fields)


def mode_error(config: ScanConfig) -> str | None:
    """Why an LMS111 refuses this frequency/resolution, or None (for callers' messages)."""
    key = (config.scan_frequency_100th_hz, config.angular_resolution_10000th_deg)
    if key in SUPPORTED_MODES:
        return None
    return (
        f"{config.scan_frequency_hz:g} Hz at {config.angular_resolution_deg:g}° is not an "
        "LMS111 mode (25 Hz at 0.25° or 0.5°, 50 Hz at 0.5°)"
    )
