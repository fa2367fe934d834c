"""The safe-stop hook: throttle 0, brake on, steering handed back to the operator.

It runs on every way out of automatic control: a critical service failing, a latched
error, a signal, a crash of the daemon's own main task. Targets are called synchronously
and must not block (a CAN ``send`` or a serial ``write`` of one frame), so the hook also
works from a signal handler's forced exit where no event loop can be trusted. One failing
target never prevents the others from being told: each is tried, failures are reported.
The lower layers' own command timeouts (PC104 and boards stop when commands stop) remain
the last line of defence when even this cannot run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import structlog
from structlog.typing import FilteringBoundLogger

log: FilteringBoundLogger = structlog.get_logger(component="safety")


@dataclass(frozen=True)
class SafeCommand:
    """What every actuator is told when control is revoked."""

    throttle_pct: float
    brake_pct: float
    decel_mps2: float
    steering_released: bool = True

    def __post_init__(self) -> None:
        if self.throttle_pct != 0.0:
            raise ValueError("a safe command never opens the throttle")
        if not 0.0 < self.brake_pct <= 100.0:
            raise ValueError(f"a safe command applies the brake (got brake_pct={self.brake_pct})")
        if not self.steering_released:
            raise ValueError("a safe command hands steering back to the operator")


class SafeStopTarget(Protocol):
    """An actuator path that can be put in its safe state without blocking."""

    @property
    def name(self) -> str: ...

    def command_safe_state(self, command: SafeCommand, reason: str) -> None: ...


@dataclass(frozen=True)
class SafeStopResult:
    reason: str
    commanded: tuple[str, ...]
    failed: tuple[tuple[str, str], ...]


class SafeStop:
    """Fans the safe command out to every registered actuator path."""

    def __init__(self, command: SafeCommand, targets: list[SafeStopTarget] | None = None) -> None:
        self.command = command
        self._targets: list[SafeStopTarget] = list(targets or [])
        self.engagements = 0

    def add_target(self, target: SafeStopTarget) -> None:
        self._targets.append(target)

    def engage(self, reason: str) -> SafeStopResult:
        self.engagements += 1
        commanded: list[str] = []
        failed: list[tuple[str, str]] = []
        for target in self._targets:
            try:
                target.command_safe_state(self.command, reason)
            except Exception as exc:  # one broken path must not silence the others
                failed.append((target.name, f"{type(exc).__name__}: {exc}"))
            else:
                commanded.append(target.name)
        result = SafeStopResult(reason, tuple(commanded), tuple(failed))
        log_method = log.error if failed or not self._targets else log.warning
        log_method(
            "safe_stop",
            reason=reason,
            throttle_pct=self.command.throttle_pct,
            brake_pct=self.command.brake_pct,
            steering="released",
            commanded=list(commanded),
            failed=[f"{name}: {error}" for name, error in failed],
            note=None if self._targets else "no actuator path registered",
        )
        return result
