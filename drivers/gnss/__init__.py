"""GNSS/INS position input, sans-I/O: NMEA 0183 lines in, typed events in SI units out.

`NmeaReceiver` splits and verifies lines (checksum required) and counts what it rejects;
`drivers.gnss.sentences` says what the fields of GGA, RMC, VTG, HDT, THS and GST mean. The
serial reader that feeds it lives elsewhere (issue 12).
"""

from drivers.gnss.nmea import NmeaReceiver, Reject, nmea_checksum
from drivers.gnss.sentences import (
    FixQuality,
    GgaFix,
    GstError,
    Heading,
    NmeaEvent,
    RmcFix,
    ThsMode,
    VtgVelocity,
)

__all__ = [
    "FixQuality",
    "GgaFix",
    "GstError",
    "Heading",
    "NmeaEvent",
    "NmeaReceiver",
    "Reject",
    "RmcFix",
    "ThsMode",
    "VtgVelocity",
    "nmea_checksum",
]
