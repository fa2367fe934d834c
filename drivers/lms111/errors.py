"""The one exception the LMS111 protocol core raises.

Everything that comes off the wire is untrusted: a truncated telegram, a flipped checksum, a
token that is not a number, a length that points past the end. All of it surfaces as
`ProtocolError` and nothing else, so the asyncio client needs exactly one ``except`` around
its read-feed-drain loop (the rule h11 follows). Encoding a value that does not fit its
field (a password wider than 32 bits, a float32 overflow) raises it too: one type for "this
is not a valid CoLa telegram", whichever direction. One subclass, `TruncatedTelegram`, tells
a cut-off CoLa-A frame apart, which a device (the twin) must ignore rather than refuse.
"""

from __future__ import annotations


class ProtocolError(Exception):
    """Bad CoLa input (or output that cannot be encoded).

    When the framer raises it, it has already discarded the offending bytes: the next
    `next_event()` continues with whatever followed, so one corrupted telegram never stalls
    a scanner stream.
    """


class TruncatedTelegram(ProtocolError):
    """A CoLa-A telegram cut off by a new STX before its ETX (already dropped).

    A `ProtocolError` like any other for a host reading a scanner. A device, though, drops it
    without an answer: to a CoLa-A LMS1xx, a CoLa-B request (``02 02 02 02`` + length +
    payload) is exactly such a cut-off frame, and an LMS100 stays silent to it (sick_scan_xd
    #419), which is how SOPAS drivers find out which dialect a scanner talks.
    """
