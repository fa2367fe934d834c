"""The simulated LMS111's field-evaluation telegrams: fields, digital inputs, outputs.

The twin has no field evaluation configured, which is what these answers say. They matter
because SICK's ``sick_scan_xd`` reads them at start-up (its LMS1xx launch uses the "LMS5xx"
field logic with 30 fields) and gives up on any ``sFA``: ``sRN field000`` .. ``sRN
field029``, then ``sRN LIDinputstate``; later it subscribes to ``LIDinputstate`` and
``LIDoutputstate``.

``sRA fieldNNN`` (one monitoring field), in order; CoLa-B offsets count the 8-byte header
(``02 02 02 02`` + length), so the parameters start at 21, after ``sRA fieldNNN ``:

* 21 distance scale factor, REAL (float32): 1.0 (mm, as the scans);
* 25 distance scale offset, REAL: 0.0;
* 29 angle scale factor, uint32 (1/10000°): 5000 (0.5° per segment index);
* 33 angle scale offset, int32 (1/10000°): -450000 (-45°, the first beam);
* 37 field type, uint8: 2 (segmented);
* 38 field number, uint8: NNN + 1;
* 39 segmented field configured, uint16: 0 (if 1: a uint16 count, then per point angle
  index, start and stop distance, uint16 each);
* 41 rectangular field configured, uint16: 0 (if 1: 18 more bytes);
* 43 radial field configured, uint16: 0 (always 0 for sick_scan_xd);
* 45 dynamic field configured, uint16: 0 (if 1: 24 more bytes);
* 47 a trailer sick_scan_xd does not read, meaning not documented in the sources reached:
  uint16 1, a flexible string (the field's name in both sets of answers; empty here), uint16 0.

54 bytes framed in CoLa-B (sick_scan_xd needs at least 41); in CoLa-A the same values as
tokens: ``sRA field000 3F800000 00000000 1388 FFF92230 2 1 0 0 0 0 1 0 0``.

Sources: sick_scan_xd's ``SickScanFieldMonSingleton::parseBinaryDatagram`` (the offsets;
it takes the field's index from the telegram's name and ignores the number byte) and two
sets of device answers in its test code: an LMS511's (firmware V1.80, recorded in
``test/emulator/test_server.py``) and a TiM7xxS's (``testcase_generator.cpp``, from a
capture it names ``20210113_tim871s_elephant.pcapng``). Both send type 2 with no
segments for an empty field, and the same 6-byte trailer. Decided from them: type 2, not 0
(which sick_scan_xd's ``SickScanMonFieldType`` calls radial, "not supported"); the field
number 1-based as both devices number their configured fields (the TiM7xxS every field; the
LMS511 sends 0 for its unconfigured ones). SICK's telegram listing itself (8014631) was
not available.

``sRA LIDinputstate``: version (uint16, 0), system counter (uint32, the µs clock here), the
state of 4 inputs (uint8 each, all 0: inputs open, field set 1), time state (uint16, **0**:
no time stamp follows; with 1, year uint16, month, day, hour, minute, second uint8 and µs
uint32 would follow, as in the LMS511's recorded answer). sick_scan_xd's
``parseBinaryLIDinputstateMsg`` reads the inputs at offsets 32..35 and the time state at 36;
sick_scan_xd's own TiM7xx emulator answers the same 12 bytes, time state 0.

``sRA LIDoutputstate`` (from an LMS1xx capture): version, system counter, 3 outputs (state
uint8, count uint32), 8 external outputs (state 2 = not used, count), time state 0.
"""

from __future__ import annotations

import re
from typing import Final

from drivers.lms111.cola import Command, CommandType
from drivers.lms111.values import F32, FLEXSTR, I32, U8, U16, U32, FieldType, Value

FIELD_COUNT: Final = 30  # field000 .. field029, as sick_scan_xd reads them from an LMS1xx
FIELD_DISTANCE_SCALE: Final = 1.0
FIELD_DISTANCE_OFFSET: Final = 0.0
FIELD_ANGLE_SCALE_10000TH_DEG: Final = 5000
FIELD_ANGLE_OFFSET_10000TH_DEG: Final = -450_000
SEGMENTED_FIELD: Final = 2  # sick_scan_xd: 0 radial, 1 rectangle, 2 segmented, 3 dynamic
INPUT_COUNT: Final = 4
_FIELD_NAME: Final = re.compile(r"field([0-9]{3})")


def field_index(name: str) -> int | None:
    """NNN of ``fieldNNN`` if the device has that field (0 .. 29), else None."""
    match = _FIELD_NAME.fullmatch(name)
    if match is None:
        return None
    index = int(match.group(1))
    return index if index < FIELD_COUNT else None


def answer_field(index: int) -> Command:
    """``sRA fieldNNN`` describing an unconfigured field (see the module docstring)."""
    fields: tuple[tuple[FieldType, Value], ...] = (
        (F32, FIELD_DISTANCE_SCALE),
        (F32, FIELD_DISTANCE_OFFSET),
        (U32, FIELD_ANGLE_SCALE_10000TH_DEG),
        (I32, FIELD_ANGLE_OFFSET_10000TH_DEG),
        (U8, SEGMENTED_FIELD),
        (U8, index + 1),
        (U16, 0),  # segmented field configured
        (U16, 0),  # rectangular field configured
        (U16, 0),  # radial field configured
        (U16, 0),  # dynamic field configured
        (U16, 1),  # the trailer both sets of device answers end with
        (FLEXSTR, ""),
        (U16, 0),
    )
    return Command(CommandType.SRA, f"field{index:03d}", fields)


def answer_input_state(system_counter_us: int) -> Command:
    """``sRA LIDinputstate``: all 4 inputs open, no time stamp."""
    fields: list[tuple[FieldType, Value]] = [(U16, 0), (U32, system_counter_us)]
    fields += [(U8, 0)] * INPUT_COUNT + [(U16, 0)]
    return Command(CommandType.SRA, "LIDinputstate", tuple(fields))


def answer_output_state(system_counter_us: int) -> Command:
    """``sRA LIDoutputstate``: 3 outputs off, 8 external ones not used, no time stamp."""
    fields: list[tuple[FieldType, Value]] = [(U16, 1), (U32, system_counter_us)]
    fields += [(U8, 0), (U32, 0)] * 3 + [(U8, 2), (U32, 0)] * 8 + [(U16, 0)]
    return Command(CommandType.SRA, "LIDoutputstate", tuple(fields))
