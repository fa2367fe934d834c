"""SOPAS CoLa telegrams: command types, typed events, errors, and outgoing commands.

Every telegram is ``<3-letter command type> <name>[ <parameters>]`` in both dialects: the
type and name are ASCII followed by a space; the parameters are tokens (CoLa-A) or big-endian
binary (CoLa-B), see `values`. The one exception is the error answer ``sFA``, which carries
no name: ``sFA 5`` in CoLa-A, ``sFA`` + uint16 code in CoLa-B (``73 46 41 00 0A``).

The sFA table is SOPAS's error enumeration, in order, as listed by SICK's drivers
(``sick_scan_xd``'s ``sick_err_t``, the LMS1xx Python examples) and Wireshark's dissector;
the codes are hexadecimal in CoLa-A (``sFA 11`` = 17 = invalid CoLa-A character).
"""

from __future__ import annotations

import enum
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import Dialect, Telegram, frame
from drivers.lms111.scan import Scan
from drivers.lms111.scandata import decode_scan, encode_scan_params
from drivers.lms111.values import FieldType, ParamReader, Value, decode_params, encode_params


class CommandType(enum.Enum):
    SRN = "sRN"  # read variable by name
    SRA = "sRA"  # read answer
    SWN = "sWN"  # write variable by name
    SWA = "sWA"  # write answer
    SMN = "sMN"  # call method by name
    SAN = "sAN"  # method answer
    SMA = "sMA"  # method accepted (asynchronous methods)
    SEN = "sEN"  # subscribe / unsubscribe an event
    SEA = "sEA"  # event subscription answer
    SSN = "sSN"  # event telegram (a subscribed variable, e.g. each scan)
    SFA = "sFA"  # error answer


SOPAS_ERRORS: Final[dict[int, tuple[str, str]]] = {
    0x00: ("Sopas_Ok", "no error"),
    0x01: ("Sopas_Error_METHODIN_ACCESSDENIED", "access denied: wrong user level"),
    0x02: ("Sopas_Error_METHODIN_UNKNOWNINDEX", "unknown method index or name"),
    0x03: ("Sopas_Error_VARIABLE_UNKNOWNINDEX", "unknown variable index or name"),
    0x04: ("Sopas_Error_LOCALCONDITIONFAILED", "local condition failed: value out of range"),
    0x05: ("Sopas_Error_INVALID_DATA", "invalid data"),
    0x06: ("Sopas_Error_UNKNOWN_ERROR", "unknown error"),
    0x07: ("Sopas_Error_BUFFER_OVERFLOW", "buffer overflow: answer too large"),
    0x08: ("Sopas_Error_BUFFER_UNDERFLOW", "buffer underflow: more data expected"),
    0x09: ("Sopas_Error_ERROR_UNKNOWN_TYPE", "unknown variable type"),
    0x0A: ("Sopas_Error_VARIABLE_WRITE_ACCESSDENIED", "write access denied: read-only"),
    0x0B: ("Sopas_Error_UNKNOWN_CMD_FOR_NAMESERVER", "command unknown to the name server"),
    0x0C: ("Sopas_Error_UNKNOWN_COLA_COMMAND", "unknown CoLa command"),
    0x0D: ("Sopas_Error_METHODIN_SERVER_BUSY", "server busy: one command at a time"),
    0x0E: ("Sopas_Error_FLEX_OUT_OF_BOUNDS", "flexible array or string out of bounds"),
    0x0F: ("Sopas_Error_EVENTREG_UNKNOWNINDEX", "unknown event"),
    0x10: ("Sopas_Error_COLA_A_VALUE_OVERFLOW", "CoLa-A value overflow: value too large"),
    0x11: ("Sopas_Error_COLA_A_INVALID_CHARACTER", "invalid CoLa-A character"),
    0x12: ("Sopas_Error_OSAI_NO_MESSAGE", "no operating system message (GET)"),
    0x13: ("Sopas_Error_OSAI_NO_ANSWER_MESSAGE", "no operating system message (PUT)"),
    0x14: ("Sopas_Error_INTERNAL", "internal firmware error"),
    0x15: ("Sopas_Error_HubAddressCorrupted", "hub address too short or too long"),
    0x16: ("Sopas_Error_HubAddressDecoding", "hub address cannot be decoded"),
    0x17: ("Sopas_Error_HubAddressAddressExceeded", "too many hubs in the address"),
    0x18: ("Sopas_Error_HubAddressBlankExpected", "blank expected in the hub address"),
    0x19: ("Sopas_Error_AsyncMethodsAreSuppressed", "asynchronous methods are suppressed"),
    0x1A: ("Sopas_Error_ComplexArraysNotSupported", "complex arrays not supported"),
}

_NAME = re.compile(rb"[A-Za-z0-9_]{1,64}")


@dataclass(frozen=True)
class ErrorReply:
    """``sFA``: the device refused the last request."""

    code: int
    meaning: str

    @classmethod
    def from_code(cls, code: int) -> ErrorReply:
        return cls(code, SOPAS_ERRORS.get(code, ("", f"unknown SOPAS error {code:#x}"))[1])

    @property
    def constant(self) -> str:
        """SOPAS's name for the code, e.g. ``Sopas_Error_METHODIN_ACCESSDENIED``."""
        return SOPAS_ERRORS.get(self.code, (f"Sopas_Error_{self.code:#x}", ""))[0]


@dataclass(frozen=True)
class Reply:
    """Any telegram other than a scan or an error: answers, and the requests a twin receives.

    ``params`` are the raw parameter bytes in ``dialect``; `fields` splits CoLa-A ones into
    tokens and `decode` reads typed values in either dialect.
    """

    kind: CommandType
    name: str
    params: bytes
    dialect: Dialect

    @property
    def fields(self) -> tuple[str, ...]:
        """CoLa-A tokens (a length-prefixed string with spaces splits); () in CoLa-B."""
        if self.dialect is Dialect.COLA_B or not self.params:
            return ()
        return tuple(self.params.decode("latin-1").split(" "))

    def decode(self, fields: Sequence[FieldType], *, exact: bool = True) -> tuple[Value, ...]:
        return decode_params(self.dialect, self.params, fields, exact=exact)

    def reader(self) -> ParamReader:
        return ParamReader(self.dialect, self.params)


@dataclass(frozen=True, eq=False)
class ScanTelegram:
    """``sSN LMDscandata`` (subscribed stream) or ``sRA LMDscandata`` (polled)."""

    kind: CommandType
    scan: Scan


Event = Reply | ErrorReply | ScanTelegram


def _parse_error(rest: bytes, dialect: Dialect) -> ErrorReply:
    if dialect is Dialect.COLA_A:
        code_token = rest[1:] if rest.startswith(b" ") else rest
        try:
            if not code_token or len(code_token) > 8:
                raise ValueError
            return ErrorReply.from_code(int(code_token.decode("ascii"), 16))
        except (UnicodeDecodeError, ValueError) as exc:
            raise ProtocolError(f"bad sFA code {code_token!r}") from exc
    code_bytes = rest[1:] if len(rest) == 3 and rest[0] == 0x20 else rest
    if len(code_bytes) not in (1, 2):
        raise ProtocolError(f"bad CoLa-B sFA length {len(rest)}")
    return ErrorReply.from_code(int.from_bytes(code_bytes, "big"))


def parse_telegram(telegram: Telegram, *, host_receive_time_s: float | None = None) -> Event:
    """Type a framed telegram; `ProtocolError` for anything that is not valid CoLa.

    ``host_receive_time_s`` is stamped on a scan (the core has no clock).
    """
    payload, dialect = telegram.payload, telegram.dialect
    try:
        kind = CommandType(payload[:3].decode("ascii"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProtocolError(f"unknown command type {payload[:3]!r}") from exc
    rest = payload[3:]
    if kind is CommandType.SFA:
        return _parse_error(rest, dialect)
    if not rest.startswith(b" "):
        raise ProtocolError(f"{kind.value} is not followed by a space and a name")
    name_end = rest.find(b" ", 1)
    name = rest[1:] if name_end < 0 else rest[1:name_end]
    params = b"" if name_end < 0 else rest[name_end + 1 :]
    if not _NAME.fullmatch(name):
        raise ProtocolError(f"bad command name {name[:64]!r}")
    text_name = name.decode("ascii")
    if text_name == "LMDscandata" and kind in (CommandType.SSN, CommandType.SRA):
        try:
            scan = decode_scan(dialect, params, host_receive_time_s=host_receive_time_s)
        except (ValueError, IndexError, OverflowError, struct.error) as exc:  # belt and braces
            raise ProtocolError(f"undecodable scan: {exc}") from exc
        return ScanTelegram(kind, scan)
    return Reply(kind, text_name, params, dialect)


@dataclass(frozen=True)
class Command:
    """An outgoing telegram, dialect-free until encoded (requests, and the twin's answers)."""

    kind: CommandType
    name: str
    fields: tuple[tuple[FieldType, Value], ...] = ()

    def payload(self, dialect: Dialect) -> bytes:
        if not _NAME.fullmatch(self.name.encode("ascii", "replace")):
            raise ProtocolError(f"bad command name {self.name!r}")
        head = f"{self.kind.value} {self.name}".encode("ascii")
        if not self.fields:
            return head
        return head + b" " + encode_params(dialect, self.fields)

    def encode(self, dialect: Dialect) -> bytes:
        """The framed bytes to write to the socket."""
        return frame(dialect, self.payload(dialect))


def encode_error(code: int, dialect: Dialect) -> bytes:
    """A framed ``sFA`` answer (what the twin sends to refuse a request)."""
    if not 0 <= code <= 0xFFFF:
        raise ProtocolError(f"sFA code {code} out of range")
    if dialect is Dialect.COLA_A:
        return frame(dialect, b"sFA %X" % code)
    return frame(dialect, b"sFA" + code.to_bytes(2, "big"))


def encode_scan_telegram(
    scan: Scan, dialect: Dialect, kind: CommandType = CommandType.SSN
) -> bytes:
    """A framed ``sSN LMDscandata`` (or, for a poll, ``sRA``) telegram carrying ``scan``."""
    if kind not in (CommandType.SSN, CommandType.SRA):
        raise ProtocolError(f"a scan is sent as sSN or sRA, not {kind.value}")
    head = kind.value.encode() + b" LMDscandata "
    return frame(dialect, head + encode_scan_params(scan, dialect))
