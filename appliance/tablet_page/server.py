"""The tablet page's server: the operator page's asyncio shell with the tablet's routes.

The connection handling (limits, deadlines, a flood dropped unanswered) is the operator
page's (`appliance.operator_page.server`); what differs is that a tablet on the site's
network reaches it, so every route but the page itself goes through the gate
(`appliance.tablet_page.gate`): pairing, token, numbered requests, rate. The routes:

- ``GET /``: the page (no secret in it; its script and style pinned by hash in the CSP);
- ``POST /api/pair {"code"}``: the token, for the code shown at the vehicle;
- ``POST /api/hold {"seq", "held"}``: a heartbeat of the hold button, or its release;
- ``POST /api/select {"seq", "pallet"}``: the target pallet, by name;
- ``POST /api/state {"seq"}``: what the page draws (the merged map, the plan, the
  vehicle, the phase, whether the hold counts).

The token travels in ``Authorization: Bearer``. The Host header must name the address
the server listens on (or a name the vehicle file gives): a web page elsewhere that
resolves its own name to the vehicle (DNS rebinding) is refused.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from http import HTTPStatus
from importlib import resources
from typing import Any, Protocol

from appliance.logs import get_logger
from appliance.operator_page.http import HttpError, Request, error_response, render_response
from appliance.operator_page.server import (
    JSON_TYPE,
    OperatorPage,
    host_header_name,
    json_bytes,
)
from appliance.tablet_page.gate import Paired, Refusal, TabletGate

log = get_logger("tablet_page")

MAX_BODY_BYTES = 1024  # a request is a code, a number, a flag, a pallet's name


class TabletActions(Protocol):
    """What the daemon does for the tablet: nothing the operator panel could not."""

    def hold_changed(self, held: bool, until_s: float) -> None:
        """The hold as the gate sees it now: held until ``until_s`` (monotonic) unless a
        later call says otherwise. The control loop lets it lapse at ``until_s`` itself:
        a frozen page sends nothing, so only the clock can end its hold."""

    def select(self, pallet: str) -> tuple[bool, str]:
        """Make ``pallet`` the target; (accepted, why not)."""

    def state(self) -> dict[str, Any]:
        """What the page draws."""


def load_tablet_page() -> bytes:
    return resources.files("appliance.tablet_page").joinpath("static/tablet.html").read_bytes()


class TabletPage(OperatorPage):
    """The tablet's page and API, served by the daemon as a supervised service."""

    max_body_bytes = MAX_BODY_BYTES

    def __init__(
        self,
        gate: TabletGate,
        actions: TabletActions,
        host: str,
        port: int,
        *,
        host_names: tuple[str, ...] = (),
        clock: Callable[[], float] = time.monotonic,
        max_connections: int = 8,
        request_timeout_s: float = 2.0,
        page: bytes | None = None,
    ) -> None:
        super().__init__(
            actions.state,
            None,
            host,
            port,
            allow_non_loopback=True,
            max_connections=max_connections,
            request_timeout_s=request_timeout_s,
            page=load_tablet_page() if page is None else page,
        )
        self.gate = gate
        self.actions = actions
        self.clock = clock
        self.host_names = {host.lower(), *(name.lower() for name in host_names)}

    def respond(self, request: Request) -> bytes:
        head_only = request.method == "HEAD"
        try:
            self._check_host(request)
            if request.path == "/" and request.method in ("GET", "HEAD"):
                return render_response(
                    HTTPStatus.OK,
                    self.page,
                    "text/html; charset=utf-8",
                    head_only=head_only,
                    csp=self.csp,
                )
            if not request.path.startswith("/api/"):
                raise HttpError(HTTPStatus.NOT_FOUND, "no such page")
            if request.method != "POST":
                raise HttpError(HTTPStatus.METHOD_NOT_ALLOWED, "the API takes POST")
            status, document = self._api(request)
        except HttpError as error:
            return error_response(error, head_only=head_only)
        return render_response(status, json_bytes(document), JSON_TYPE, csp=self.csp)

    def _check_host(self, request: Request) -> None:
        host = request.header("host")
        if host is None or host_header_name(host).lower() not in self.host_names:
            raise HttpError(HTTPStatus.MISDIRECTED_REQUEST, "Host is not this vehicle's address")

    def _api(self, request: Request) -> tuple[HTTPStatus, dict[str, Any]]:
        body = _json_object(request.body)
        now_s = self.clock()
        if request.path == "/api/pair":
            paired = self.gate.pair(body.get("code"), now_s)
            if isinstance(paired, Refusal):
                return _refused(paired)
            log.info("tablet_paired")
            self.actions.hold_changed(False, now_s)
            return HTTPStatus.OK, {"token": paired.token}
        token = _bearer(request)
        seq = body.get("seq")
        if request.path == "/api/hold":
            refused = self.gate.hold(token, seq, body.get("held"), now_s)
            if refused is not None:
                return _refused(refused)
            held = self.gate.held(now_s)
            self.actions.hold_changed(held, now_s + self.gate.params.hold_timeout_s)
            return HTTPStatus.OK, {"held": held}
        if request.path not in ("/api/select", "/api/state"):
            raise HttpError(HTTPStatus.NOT_FOUND, "no such request")
        refused = self.gate.authorize(token, seq, now_s)
        if refused is not None:
            return _refused(refused)
        if request.path == "/api/select":
            pallet = body.get("pallet")
            if not isinstance(pallet, str) or not 0 < len(pallet) <= 128:
                raise HttpError(HTTPStatus.BAD_REQUEST, "pallet must be a pallet's name")
            accepted, why = self.actions.select(pallet)
            return (HTTPStatus.OK if accepted else HTTPStatus.CONFLICT), {
                "selected": accepted,
                "reason": why,
            }
        try:
            document = dict(self.actions.state())
        except Exception as exc:
            log.error("tablet_page_state_failed", error=repr(exc))
            raise HttpError(
                HTTPStatus.INTERNAL_SERVER_ERROR, "the daemon could not produce its state"
            ) from exc
        document["held"] = self.gate.held(now_s)
        return HTTPStatus.OK, document


def _json_object(body: bytes) -> dict[str, Any]:
    try:
        value = json.loads(body.decode("utf-8")) if body else {}
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise HttpError(HTTPStatus.BAD_REQUEST, "the body is not JSON") from None
    if not isinstance(value, dict):
        raise HttpError(HTTPStatus.BAD_REQUEST, "the body is not a JSON object")
    return value


def _bearer(request: Request) -> str | None:
    value = request.header("authorization")
    if value is None or not value.startswith("Bearer "):
        return None
    return value[len("Bearer ") :].strip()


def _refused(refusal: Refusal) -> tuple[HTTPStatus, dict[str, Any]]:
    return HTTPStatus(int(refusal.status)), {"error": refusal.reason}


__all__ = ["MAX_BODY_BYTES", "Paired", "TabletActions", "TabletPage"]
