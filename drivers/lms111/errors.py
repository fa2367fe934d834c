"""The one exception the LMS111 protocol core raises.

Everything that comes off the wire is untrusted: a truncated telegram, a flipped checksum, a
token that is not a number, a length that points past the end. All of it surfaces as
`ProtocolError` and nothing else, so the asyncio client needs exactly one ``except`` around
its read-feed-drain loop (the rule h11 follows). Encoding a value that does not fit its
field (a password wider than 32 bits, a float32 overflow) raises it too: one type for "this
is not a valid CoLa telegram", whichever direction.
"""

from __future__ import annotations


class ProtocolError(Exception):
    """Bad CoLa input (or output that cannot be encoded).

    When the framer raises it, it has already discarded the offending bytes: the next
    `next_event()` continues with whatever followed, so one corrupted telegram never stalls
    a scanner stream.
    """
