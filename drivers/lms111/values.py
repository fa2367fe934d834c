"""CoLa parameter values: one field description, two encodings.

A telegram's parameters are described once, as a sequence of `FieldType` (SOPAS type + how
CoLa-A spells it), and both dialects are derived from that description:

* CoLa-A: space-separated tokens. Numbers are hexadecimal without leading zeros unless they
  start with ``+``/``-`` (signed decimal); negative values in hex are two's complement of the
  field width (``FFF92230`` = -450000 in an int32). A REAL is the 8 hex digits of its IEEE-754
  bits (``3F800000`` = 1.0). A flexible string is its length (a number) then that many raw
  bytes, which may contain spaces (an LMS sends its device name as ``B not defined``).
  Fixed strings (channel names like ``DIST1``) are bare tokens.
* CoLa-B: big-endian binary, no separators: uint8/16/32, int8/16/32, float32; a flexible
  string is a uint16 length then the bytes (as in ``sRA FirmwareVersion \\x00\\x04V5.0``).

`ParamReader` also decodes whole arrays at once (numpy): the scan telegram carries thousands of
values and a Python loop per point would miss the decode budget by an order of magnitude.
"""

from __future__ import annotations

import enum
import functools
import re
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import Dialect


class CType(enum.Enum):
    """SOPAS value types: (CoLa-B struct code, bits, signed)."""

    U8 = (">B", 8, False)
    U16 = (">H", 16, False)
    U32 = (">I", 32, False)
    I8 = (">b", 8, True)
    I16 = (">h", 16, True)
    I32 = (">i", 32, True)
    F32 = (">f", 32, False)
    FLEXSTR = ("flex", 0, False)
    FIXSTR = ("fixed", 0, False)


class Style(enum.Enum):
    """How CoLa-A spells an integer: the telegram listing uses each of these."""

    HEX = "hex"  # 1388, FFF92230 (leading zeros dropped)
    HEX2 = "hex2"  # 03, 01 00 (at least two digits: user level, channel bytes)
    HEX8 = "hex8"  # F4724744 (exactly eight digits: password, REAL bits)
    DEC = "dec"  # +5000, -450000 (signed decimal, as the listing writes requests)


@dataclass(frozen=True)
class FieldType:
    ctype: CType
    style: Style = Style.HEX
    size: int = 0  # FIXSTR only: the byte length in CoLa-B


U8: Final = FieldType(CType.U8)
U8_HEX2: Final = FieldType(CType.U8, Style.HEX2)
U16: Final = FieldType(CType.U16)
U16_DEC: Final = FieldType(CType.U16, Style.DEC)
U32: Final = FieldType(CType.U32)
U32_HEX8: Final = FieldType(CType.U32, Style.HEX8)
U32_DEC: Final = FieldType(CType.U32, Style.DEC)
I16: Final = FieldType(CType.I16)
I32: Final = FieldType(CType.I32)
I32_DEC: Final = FieldType(CType.I32, Style.DEC)
F32: Final = FieldType(CType.F32, Style.HEX8)
FLEXSTR: Final = FieldType(CType.FLEXSTR)
FLEXSTR_DEC: Final = FieldType(CType.FLEXSTR, Style.DEC)


def fixstr(size: int) -> FieldType:
    return FieldType(CType.FIXSTR, size=size)


Value = int | float | str
RawArray = npt.NDArray[np.unsignedinteger[Any]]

_HEX_TOKEN = re.compile(rb"[0-9A-Fa-f]{1,16}")
_DEC_TOKEN = re.compile(rb"[+-][0-9]{1,20}")
_INVALID_PAIR: Final = 0xFFFF
_PAIR_VALUE = np.full(1 << 16, _INVALID_PAIR, dtype=np.uint16)
for _first, _second in (
    (a, b) for a in b"0123456789ABCDEFabcdef" for b in b"0123456789ABCDEFabcdef"
):
    _PAIR_VALUE[(_first << 8) | _second] = int(bytes((_first, _second)), 16)
    _PAIR_VALUE[(0x20 << 8) | _second] = int(bytes((_second,)), 16)


_STRUCTS: Final[dict[CType, struct.Struct]] = {
    ctype: struct.Struct(ctype.value[0])
    for ctype in CType
    if ctype.value[0].startswith(">") and ctype is not CType.F32
}


def _int_info(ctype: CType) -> tuple[int, int, int, bool]:
    _, bits, signed = ctype.value
    if signed:
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1, bits, True
    return 0, (1 << bits) - 1, bits, False


# Looked up per token (enum attribute access is slow on the header's hot path).
_INT_INFO: Final = {ctype: _int_info(ctype) for ctype in CType}


def _int_range(ctype: CType) -> tuple[int, int]:
    lo, hi, _, _ = _INT_INFO[ctype]
    return lo, hi


# The writer's per-type facts, keyed by the member's name: a str hashes in C, while an enum
# member hashes through Python code, which cost microseconds per field on the scan path.
_WRITE_INTS: Final[dict[str, tuple[int, int, int, Callable[[int], bytes]]]] = {
    ctype.name: (*_int_range(ctype), (1 << ctype.value[1]) - 1, packer.pack)
    for ctype, packer in _STRUCTS.items()
}
# write_array in one numpy pass (see `hex_tokens`), per type: hex digits, big-endian dtype.
_ARRAY_TYPES: Final[dict[str, tuple[int, np.dtype[Any]]]] = {
    "U8": (2, np.dtype(">u1")),
    "U16": (4, np.dtype(">u2")),
}
_HEX_DIGITS: Final = np.frombuffer(b"0123456789ABCDEF", dtype=np.uint8)


@functools.cache
def _hex_tables(digits: int) -> tuple[npt.NDArray[Any], npt.NDArray[np.uint8], npt.NDArray[Any]]:
    """Every value's token ``digits`` wide with a space, its significant digits, and masks.

    Rows are 4 or 8 bytes (one uint32/uint64 each, so a lookup moves one word): the digits
    with leading zeros, a space, padding. ``keep[n]`` marks the bytes of a row to send when
    the value has ``n`` significant digits: the last n digits and the space. Built on first
    use: 576 kB for 16-bit data.
    """
    width = 4 if digits <= 3 else 8
    codes = np.arange(16**digits, dtype=np.uint32)[:, np.newaxis]
    shifts = 4 * np.arange(digits - 1, -1, -1, dtype=np.uint32)
    rows = np.zeros((16**digits, width), dtype=np.uint8)
    rows[:, :digits] = _HEX_DIGITS[(codes >> shifts) & 0xF]
    rows[:, digits] = ord(" ")
    significant = np.ones(16**digits, dtype=np.uint8)
    for power in range(1, digits):
        significant += codes[:, 0] >= 16**power
    keep = np.zeros((digits + 1, width), dtype=np.bool_)
    for count in range(1, digits + 1):
        keep[count, digits - count : digits + 1] = True
    word = np.uint32 if width == 4 else np.uint64
    return rows.view(word).ravel(), significant, keep.view(word).ravel()


def hex_tokens(values: npt.NDArray[np.integer[Any]], digits: int) -> bytes:
    """Upper-case hex without leading zeros, one token per value, single spaces between.

    The CoLa-A spelling of channel data (``0 1F4 FFFF``) in one numpy pass: each value's
    row (its digits with leading zeros, then a space) and the mask of the row's bytes to
    keep are looked up in tables of every value, the masked bytes are taken in order, and
    the trailing space is dropped. ``values`` must be integers from 0 to 16 ** digits - 1
    (unchecked: `ParamWriter.write_array` checks the range); ``digits`` is 2 or 4.
    """
    if len(values) == 0:
        return b""
    rows, significant, keep = _hex_tables(digits)
    index = values.astype(np.intp, copy=False)
    chars = rows.take(index).view(np.uint8)
    mask = keep.take(significant.take(index)).view(np.bool_)
    return chars[mask].tobytes()[:-1]


def parse_int_token(token: bytes, ctype: CType) -> int:
    """A CoLa-A number: hex (two's complement for signed types) or ``+``/``-`` decimal."""
    lo, hi, bits, signed = _INT_INFO[ctype]
    if _HEX_TOKEN.fullmatch(token):
        value = int(token, 16)
        if value >> bits:
            raise ProtocolError(f"{token!r} does not fit {ctype.name}")
        if signed and value > hi:
            value -= 1 << bits
        return value
    if _DEC_TOKEN.fullmatch(token):
        value = int(token)
        if not lo <= value <= hi:
            raise ProtocolError(f"{token!r} out of range for {ctype.name}")
        return value
    raise ProtocolError(f"{token!r} is not a CoLa-A number")


def format_int(value: int, ft: FieldType) -> bytes:
    integer = _WRITE_INTS.get(ft.ctype._name_)
    if integer is None:  # not an integer type: its width all the same, as ever
        (lo, hi), mask = _int_range(ft.ctype), (1 << ft.ctype.value[1]) - 1
    else:
        lo, hi, mask, _ = integer
    if not lo <= value <= hi:
        raise ProtocolError(f"{value} out of range for {ft.ctype.name}")
    return _format_int_token(value, ft.style, mask)


def _format_int_token(value: int, style: Style, mask: int) -> bytes:
    """The CoLa-A token of an in-range integer (``mask``: the field width's bits)."""
    if style is Style.HEX:
        return b"%X" % (value & mask)
    if style is Style.DEC:
        return b"%+d" % value
    if style is Style.HEX2:
        return b"%02X" % (value & mask)
    return b"%08X" % (value & mask)


def _float32_bits(value: float) -> int:
    try:
        packed = struct.pack(">f", value)
    except OverflowError as exc:
        raise ProtocolError(f"{value} does not fit a float32") from exc
    return int.from_bytes(packed, "big")


class ParamWriter:
    """Builds the parameter part of a telegram in one dialect."""

    def __init__(self, dialect: Dialect) -> None:
        self._ascii = dialect is Dialect.COLA_A
        self._parts: list[bytes] = []

    def write(self, ft: FieldType, value: Value) -> None:
        ctype = ft.ctype
        integer = _WRITE_INTS.get(ctype._name_)
        if integer is not None:
            if not isinstance(value, int):
                raise ProtocolError(f"{ctype.name} needs an int, got {value!r}")
            lo, hi, mask, pack = integer
            if not lo <= value <= hi:
                raise ProtocolError(f"{value} out of range for {ctype.name}")
            if self._ascii:
                self._parts.append(_format_int_token(value, ft.style, mask))
            else:
                self._parts.append(pack(value))
        elif ctype is CType.FLEXSTR or ctype is CType.FIXSTR:
            if not isinstance(value, str):
                raise ProtocolError(f"{ctype.name} needs a str, got {value!r}")
            self._string(ft, value)
        else:  # CType.F32
            if isinstance(value, str):
                raise ProtocolError(f"REAL needs a number, got {value!r}")
            bits = _float32_bits(float(value))
            self._parts.append(b"%08X" % bits if self._ascii else bits.to_bytes(4, "big"))

    def _string(self, ft: FieldType, text: str) -> None:
        try:
            raw = text.encode("latin-1")
        except UnicodeEncodeError as exc:
            raise ProtocolError(f"{text!r} is not latin-1") from exc
        if ft.ctype is CType.FIXSTR:
            if self._ascii:
                if not raw or b" " in raw:
                    raise ProtocolError(f"fixed string {text!r} must be one non-empty token")
                self._parts.append(raw)
            else:
                if len(raw) != ft.size:
                    raise ProtocolError(f"fixed string {text!r} must be {ft.size} bytes")
                self._parts.append(raw)
            return
        if len(raw) > 0xFFFF:
            raise ProtocolError("flexible string longer than 65535 bytes")
        if self._ascii:
            length = format_int(len(raw), FieldType(CType.U16, ft.style))
            self._parts.append(length + b" " + raw if raw else length)
        else:
            self._parts.append(len(raw).to_bytes(2, "big") + raw)

    def write_array(self, values: npt.NDArray[np.integer], ctype: CType) -> None:
        """Raw channel data: uint16 or uint8, hex tokens in CoLa-A (vectorised, see `hex_tokens`).

        Integer arrays of an unsigned type take the numpy path; anything else (a signed type,
        another dtype) the general one, which spells and refuses exactly the same way.
        """
        array_type = _ARRAY_TYPES.get(ctype._name_)
        if (
            array_type is None
            or not isinstance(values, np.ndarray)
            or values.ndim != 1
            or values.dtype.kind not in "ui"
        ):
            self._write_array_generally(values, ctype)
            return
        digits, big_endian = array_type
        dtype = values.dtype
        within = dtype.kind == "u" and dtype.itemsize * 2 <= digits  # uint16 data for U16
        if len(values) and not within:
            lo, hi = _int_range(ctype)
            if int(values.min()) < lo or int(values.max()) > hi:
                raise ProtocolError(f"channel data out of range for {ctype.name}")
        if self._ascii:
            if len(values):
                self._parts.append(hex_tokens(values, digits))
        else:
            self._parts.append(values.astype(big_endian).tobytes())

    def _write_array_generally(self, values: npt.NDArray[np.integer], ctype: CType) -> None:
        """One Python format per value: the reference spelling, for unusual inputs."""
        lo, hi = _int_range(ctype)
        if len(values) and (int(values.min()) < lo or int(values.max()) > hi):
            raise ProtocolError(f"channel data out of range for {ctype.name}")
        if self._ascii:
            if len(values):
                self._parts.append(" ".join(map("%X".__mod__, values.tolist())).encode())
        else:
            self._parts.append(values.astype(ctype.value[0]).tobytes())

    def getvalue(self) -> bytes:
        return (b" " if self._ascii else b"").join(self._parts)


def encode_params(dialect: Dialect, fields: Sequence[tuple[FieldType, Value]]) -> bytes:
    writer = ParamWriter(dialect)
    for ft, value in fields:
        writer.write(ft, value)
    return writer.getvalue()


class ParamReader:
    """Reads parameters in order from a telegram's parameter bytes, in one dialect.

    Every shortfall (missing token, truncated binary field, out-of-range value) raises
    `ProtocolError`.
    """

    def __init__(self, dialect: Dialect, data: bytes, pos: int = 0) -> None:
        self._ascii = dialect is Dialect.COLA_A
        self._data = data
        self.pos = pos
        self._token_ends: npt.NDArray[np.intp] | None = None
        self._buf: npt.NDArray[np.uint8] = np.zeros(0, dtype=np.uint8)

    def at_end(self) -> bool:
        return self.pos >= len(self._data)

    def expect_end(self) -> None:
        if not self.at_end():
            raise ProtocolError(f"{len(self._data) - self.pos} unexpected trailing bytes")

    def _token(self) -> bytes:
        data, pos = self._data, self.pos
        if pos >= len(data):
            raise ProtocolError("telegram ends before an expected value")
        end = data.find(b" ", pos)
        if end < 0:
            end = len(data)
        if end == pos:
            raise ProtocolError("empty CoLa-A token (double space)")
        self.pos = min(end + 1, len(data))
        return data[pos:end]

    def _take(self, count: int) -> bytes:
        pos = self.pos
        if count < 0 or pos + count > len(self._data):
            raise ProtocolError("telegram ends inside a binary value")
        self.pos = pos + count
        return self._data[pos : pos + count]

    def read_int(self, ft: FieldType) -> int:
        if self._ascii:
            return parse_int_token(self._token(), ft.ctype)
        packer = _STRUCTS[ft.ctype]
        value: int = packer.unpack(self._take(packer.size))[0]
        return value

    def read_float(self) -> float:
        if self._ascii:
            token = self._token()
            if not _HEX_TOKEN.fullmatch(token) or len(token) > 8:
                raise ProtocolError(f"{token!r} is not a CoLa-A REAL (8 hex digits)")
            raw = int(token, 16).to_bytes(4, "big")
        else:
            raw = self._take(4)
        value: float = struct.unpack(">f", raw)[0]
        return value

    def read_str(self, ft: FieldType) -> str:
        if ft.ctype is CType.FIXSTR:
            raw = self._token() if self._ascii else self._take(ft.size)
            return raw.decode("latin-1")
        if self._ascii:
            length = self.read_int(FieldType(CType.U16))
            raw = self._take(length)
            if length and not self.at_end():
                if self._data[self.pos] != 0x20:
                    raise ProtocolError("flexible string longer than its length says")
                self.pos += 1
        else:
            raw = self._take(int.from_bytes(self._take(2), "big"))
        return raw.decode("latin-1")

    def read(self, ft: FieldType) -> Value:
        if ft.ctype is CType.F32:
            return self.read_float()
        if ft.ctype is CType.FLEXSTR or ft.ctype is CType.FIXSTR:
            return self.read_str(ft)
        return self.read_int(ft)

    def read_array(self, count: int, ctype: CType) -> RawArray:
        """``count`` raw uint16 (or uint8) values, as a read-only native-endian array."""
        native = np.uint16 if ctype is CType.U16 else np.uint8
        out: RawArray
        if count == 0:
            out = np.zeros(0, dtype=native)
        elif self._ascii:
            out = self._read_hex_array(count, 4 if ctype is CType.U16 else 2, ctype)
        else:
            raw = self._take(count * (2 if ctype is CType.U16 else 1))
            out = np.frombuffer(raw, dtype=">u2" if ctype is CType.U16 else np.uint8).astype(native)
        out.flags.writeable = False
        return out

    def _read_hex_array(self, count: int, width: int, ctype: CType) -> RawArray:
        """Vectorised: token ends from the space positions, digits two at a time.

        A token of at most 4 hex digits is read through the two character pairs that end it,
        each looked up in a 64 K table (``" A"`` counts as the single digit A); the upper pair
        is ignored for tokens of 1-2 digits, where it belongs to the previous token. Anything
        unusual (a longer or decimal token, a bad character) takes the exact slow path.
        """
        data = self._data
        if self._token_ends is None:
            self._buf = np.frombuffer(data, dtype=np.uint8)
            self._token_ends = np.append(np.flatnonzero(self._buf == 0x20), len(data))
        ends_all = self._token_ends
        first = int(np.searchsorted(ends_all, self.pos))
        if first + count > len(ends_all):
            raise ProtocolError("telegram ends inside channel data")
        ends = ends_all[first : first + count]
        lengths = np.empty_like(ends)
        lengths[0] = ends[0] - self.pos
        np.subtract(ends[1:], ends[:-1] + 1, out=lengths[1:])
        if lengths.min() < 1 or lengths.max() > width or int(ends[0]) < width:
            return self._read_tokens_slowly(count, ctype)
        buf = self._buf
        low = _PAIR_VALUE[(buf[ends - 2].astype(np.uint16) << 8) | buf[ends - 1]]
        if width == 4:
            high = _PAIR_VALUE[(buf[ends - 4].astype(np.uint16) << 8) | buf[ends - 3]]
            high[lengths <= 2] = 0
            if (low == _INVALID_PAIR).any() or (high == _INVALID_PAIR).any():
                return self._read_tokens_slowly(count, ctype)
            values = (high << 8) | low
        else:
            if (low == _INVALID_PAIR).any():
                return self._read_tokens_slowly(count, ctype)
            values = low
        self.pos = min(int(ends[-1]) + 1, len(data))
        out: RawArray = values.astype(np.uint16 if ctype is CType.U16 else np.uint8)
        return out

    def _read_tokens_slowly(self, count: int, ctype: CType) -> RawArray:
        """Exact fallback for unusual spellings (``+500`` decimal data); errors as usual."""
        values = [parse_int_token(self._token(), ctype) for _ in range(count)]
        out: RawArray = np.asarray(values, dtype=np.uint16 if ctype is CType.U16 else np.uint8)
        return out


def decode_params(
    dialect: Dialect, data: bytes, fields: Sequence[FieldType], *, exact: bool = True
) -> tuple[Value, ...]:
    """Decode ``fields`` in order; with ``exact`` the parameters must end right after."""
    reader = ParamReader(dialect, data)
    values = tuple(reader.read(ft) for ft in fields)
    if exact:
        reader.expect_end()
    return values
