"""A recorded message's JSON text to values: `json.loads`'s answer, quicker.

Replay parses every cycle's few kilobytes of JSON (the inputs the core saw, the output it
made) and every scan's; `json.loads` was a large share of replay's time. pydantic-core's
`from_json` (pydantic is a dependency already) parses the same text several times faster.
Where the two disagree, `json.loads` is the reference and its answer is the one returned:
`from_json` refuses some text `json.loads` accepts (a lone surrogate escape, a byte-order
mark, UTF-16 or UTF-32), so a refusal is retried with `json.loads`, which gives the value
or the error the codec has always seen. Where both accept they agree, the tests check
(every float to the bit, ``NaN``/``Infinity``/``-Infinity`` as float specials, big
integers, duplicate keys: the last wins).
"""

from __future__ import annotations

import json
from typing import Any

from pydantic_core import from_json


def loads(text: bytes | str) -> Any:
    """``json.loads(text)``, by the faster parser wherever it gives the same value."""
    try:
        return from_json(text)
    except ValueError:
        return json.loads(text)
