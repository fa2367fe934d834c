"""Who may use the tablet page, and whether its hold-to-move button is held: without I/O.

Kinouchi et al.'s worker guides the forklift from a tablet: the vehicle moves only while
the button is held (Fig. 6). A tablet reaches the vehicle over the site's network, so
this is the daemon's first listener that anything but the vehicle's own PC can reach,
and every rule here is deny-by-default:

- **Pairing.** A short code, shown only at the vehicle (the operator display, `dbw
  status`), exchanged once for a session token. One tablet at a time: pairing another
  ends the first one's session (pairing is deliberate: the code is read at the vehicle).
  The code changes after every pairing, and after a few wrong guesses pairing is locked
  for a while, so a 6-digit code cannot be guessed by trying.
- **Every request authenticated** by the token (compared in constant time) and numbered:
  a request's ``seq`` must exceed the last one accepted, so a request captured and sent
  again (replayed) is refused. Without TLS on the site network a listener could read the
  token; the rules stop every other device, a stale or duplicated request, and a flood
  (a per-session rate limit; the server also bounds connections), not an eavesdropper
  who can forge requests (README, Forklift: keep the tablet on the vehicle's own WLAN).
- **The hold** is a heartbeat: the page sends ``held`` every `BEAT_PERIOD_S` while the
  button is pressed; the hold lasts `TabletParams.hold_timeout_s` after the last beat
  and ends at once on an explicit release. A dropped connection or a frozen page stops
  sending, so the hold lapses within the timeout and the mode machine's hold-to-move
  stops the vehicle. The hold is the panel's ENGAGE button held, nothing more.

Time is an argument and randomness is injected (``random_bytes``), so the tests run the
rules at any pace and replay is exact.
"""

from __future__ import annotations

import hmac
import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

BEAT_PERIOD_S = 0.1  # the page's heartbeat while the button is held


@dataclass(frozen=True)
class TabletParams:
    # Three beats missed and the hold lapses: long enough for a Wi-Fi hiccup, short
    # enough that a vehicle at a walking pace stops within a few decimetres.
    hold_timeout_s: float = 0.3
    code_digits: int = 6
    max_pairing_failures: int = 5
    pairing_lockout_s: float = 60.0
    # A paired tablet that says nothing for this long must pair again.
    session_idle_s: float = 600.0
    # Per session: the beats are 10 a second, a person's taps a few more.
    max_requests_per_s: float = 40.0
    burst_requests: int = 20

    def __post_init__(self) -> None:
        if not 0.05 <= self.hold_timeout_s <= 5.0:
            raise ValueError(f"hold_timeout_s must be in [0.05, 5] s, got {self.hold_timeout_s}")
        if not 4 <= self.code_digits <= 12:
            raise ValueError(f"code_digits must be 4 to 12, got {self.code_digits}")
        if self.max_pairing_failures < 1 or not self.pairing_lockout_s > 0.0:
            raise ValueError("pairing needs max_pairing_failures >= 1 and a lockout > 0")
        if not (self.max_requests_per_s > 0.0 and self.burst_requests >= 1):
            raise ValueError("the rate limit needs a positive rate and a burst >= 1")


class Status(IntEnum):
    """The HTTP status a refusal is answered with."""

    OK = 200
    BAD_REQUEST = 400
    UNAUTHORIZED = 401
    FORBIDDEN = 403
    CONFLICT = 409
    TOO_MANY_REQUESTS = 429


@dataclass(frozen=True)
class Refusal:
    status: Status
    reason: str


@dataclass(frozen=True)
class Paired:
    token: str


@dataclass
class _Session:
    token: str
    last_seq: int
    last_seen_s: float
    tokens_left: float  # the rate limit's bucket
    bucket_s: float


class TabletGate:
    """The pairing, the session and the hold; see the module doc."""

    def __init__(
        self, random_bytes: Callable[[int], bytes], params: TabletParams | None = None
    ) -> None:
        self.params = params or TabletParams()
        self._random = random_bytes
        self.reset()

    def reset(self) -> None:
        """No session, no hold, a fresh code (the daemon's start)."""
        self._session: _Session | None = None
        self._failures = 0
        self._locked_until_s = -math.inf
        self._holding = False
        self._hold_until_s = -math.inf
        self.code = self._new_code()
        self.refusals = 0

    # ---- pairing ---------------------------------------------------------------------
    def _new_code(self) -> str:
        digits = self.params.code_digits
        number = int.from_bytes(self._random(8), "big") % 10**digits
        return f"{number:0{digits}d}"

    def pair(self, code: object, now_s: float) -> Paired | Refusal:
        """A tablet offers the code shown at the vehicle; a token if it is right."""
        if now_s < self._locked_until_s:
            wait = self._locked_until_s - now_s
            return self._refuse(Status.TOO_MANY_REQUESTS, f"pairing locked for {wait:.0f} s")
        if not isinstance(code, str) or not hmac.compare_digest(code.encode(), self.code.encode()):
            self._failures += 1
            if self._failures >= self.params.max_pairing_failures:
                self._failures = 0
                self._locked_until_s = now_s + self.params.pairing_lockout_s
                self.code = self._new_code()  # a locked-out guesser starts over
            return self._refuse(Status.FORBIDDEN, "wrong pairing code")
        self._failures = 0
        self.code = self._new_code()
        self._release()  # a new tablet starts with nothing held
        token = self._random(16).hex()
        self._session = _Session(token, 0, now_s, float(self.params.burst_requests), now_s)
        return Paired(token)

    @property
    def paired(self) -> bool:
        return self._session is not None

    def unpair(self) -> None:
        """End the session (a new code asked for; the daemon has no command for it yet)."""
        self._session = None
        self._release()

    # ---- every request after pairing ---------------------------------------------------
    def authorize(self, token: object, seq: object, now_s: float) -> Refusal | None:
        """None when the request may proceed; its ``seq`` is then the session's last."""
        session = self._session
        if session is not None and now_s - session.last_seen_s > self.params.session_idle_s:
            self.unpair()
            session = None
        if session is None:
            return self._refuse(Status.UNAUTHORIZED, "not paired: enter the code shown")
        if not isinstance(token, str) or not hmac.compare_digest(
            token.encode(), session.token.encode()
        ):
            return self._refuse(Status.UNAUTHORIZED, "wrong token")
        if not (isinstance(seq, int) and not isinstance(seq, bool) and 0 < seq < 2**53):
            return self._refuse(Status.BAD_REQUEST, "seq must be a positive integer")
        if seq <= session.last_seq:
            return self._refuse(Status.CONFLICT, f"seq {seq} already used (replayed?)")
        p = self.params
        elapsed = max(0.0, now_s - session.bucket_s)
        bucket = min(float(p.burst_requests), session.tokens_left + elapsed * p.max_requests_per_s)
        session.bucket_s = now_s
        if bucket < 1.0:
            session.tokens_left = bucket
            return self._refuse(Status.TOO_MANY_REQUESTS, "too many requests")
        session.tokens_left = bucket - 1.0
        session.last_seq = seq
        session.last_seen_s = now_s
        return None

    def _refuse(self, status: Status, reason: str) -> Refusal:
        self.refusals += 1
        return Refusal(status, reason)

    # ---- the hold ----------------------------------------------------------------------
    def hold(self, token: object, seq: object, held: object, now_s: float) -> Refusal | None:
        """A heartbeat of the button: ``held`` True renews the hold, False ends it now."""
        refused = self.authorize(token, seq, now_s)
        if refused is not None:
            return refused
        if not isinstance(held, bool):
            return self._refuse(Status.BAD_REQUEST, "held must be true or false")
        if held:
            self._holding = True
            self._hold_until_s = now_s + self.params.hold_timeout_s
        else:
            self._release()
        return None

    def _release(self) -> None:
        self._holding = False
        self._hold_until_s = -math.inf

    def held(self, now_s: float) -> bool:
        """Whether the button counts as held now: a beat within the timeout, no release."""
        if self._holding and now_s > self._hold_until_s:
            self._release()  # lapsed: a later beat must press it again
        return self._holding
