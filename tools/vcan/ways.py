"""Choosing the way to a kernel with vcan: each way either gives a Kernel that passed
its probe or raises WayFailed with a reason; the first that works is taken, and when
none does, one line names every way tried and why it failed."""

from __future__ import annotations

import os
import platform
import shutil
import socket
import subprocess
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path

from . import qemu, uml
from .common import EXIT_TIMEOUT, PROJECT_ROOT, Kernel, WayFailed, log

# Testing's UML before the system's: where both boot, the guest's system calls cost half
# as much under testing's (seccomp mode, tools/vcan/uml.py), and the daemon's operator
# session over vcan ran with control jitter p99 11-33 ms (5 of 5 passed, 18 s each)
# against 44-229 ms with bookworm's (4 of 5 passed, 22-41 s), on the same machine in turn.
# The system's stays the fallback when testing's cannot be fetched.
WAYS = ("native", "uml-testing", "uml-system", "qemu")


class NoWay(Exception):
    def __init__(self, failures: Sequence[tuple[str, str]]) -> None:
        super().__init__(failure_line(failures))
        self.failures = list(failures)


def failure_line(failures: Sequence[tuple[str, str]]) -> str:
    """One line naming every way tried and why it failed."""
    tried = "; ".join(f"{way}: {' '.join(why.split())}" for way, why in failures)
    return f"vcan_run: no kernel with SocketCAN vcan found ({tried})"


def select(order: Sequence[str], finders: Mapping[str, Callable[[], Kernel]]) -> Kernel:
    """The Kernel of the first way in ``order`` whose finder succeeds; NoWay otherwise."""
    failures: list[tuple[str, str]] = []
    for way in order:
        try:
            return finders[way]()
        except Exception as exc:  # an unforeseen error (a full disk, say) fails this way only
            why = str(exc) if isinstance(exc, WayFailed) else f"{type(exc).__name__}: {exc}"
            failures.append((way, why))
            if way != order[-1]:
                log(f"{way} does not work here ({why}); trying the next way")
    raise NoWay(failures)


def order_for(way: str) -> tuple[str, ...]:
    return WAYS if way == "auto" else (way,)


def cache_dir(environ: Mapping[str, str] | None = None) -> Path:
    """``${XDG_CACHE_HOME:-$HOME/.cache}/dbw-applique/vcan``."""
    env = os.environ if environ is None else environ
    base = env.get("XDG_CACHE_HOME") or str(Path(env.get("HOME") or Path.home()) / ".cache")
    return Path(base) / "dbw-applique" / "vcan"


def native_problem() -> str | None:
    """Why this kernel cannot give us an up vcan0 (None when it can)."""
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (AttributeError, OSError) as exc:
        return f"host kernel {platform.release()} has no SocketCAN ({exc})"
    ip = shutil.which("ip")
    if ip is None:
        return None if Path("/sys/class/net/vcan0").exists() else "no vcan0 and no ip(8)"
    if not Path("/sys/class/net/vcan0").exists():
        add = [ip, "link", "add", "dev", "vcan0", "type", "vcan"]
        done = subprocess.run(add, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            return f"cannot add vcan0: {done.stderr.strip()[:120]}"
    up = subprocess.run([ip, "link", "set", "up", "vcan0"], capture_output=True, text=True)
    return None if up.returncode == 0 else f"cannot set vcan0 up: {up.stderr.strip()[:120]}"


def run_native(cmd: list[str], timeout_s: float) -> int:
    try:
        return subprocess.run(cmd, cwd=PROJECT_ROOT, timeout=timeout_s, check=False).returncode
    except subprocess.TimeoutExpired:
        print(f"vcan_run: pytest timed out after {timeout_s:.0f} s", flush=True)
        return EXIT_TIMEOUT


def find_native() -> Kernel:
    problem = native_problem()
    if problem:
        raise WayFailed(problem)
    return Kernel("native", f"native SocketCAN (host kernel {platform.release()})", run_native)


def seccomp_note(found: uml.Uml) -> str:
    return ", seccomp=auto" if found.seccomp else ", ptrace mode: slower system calls"


def find_uml_system(mem: str) -> Kernel:
    found = uml.system_uml()
    return Kernel(
        "uml-system",
        f"user-mode Linux {found.version} (the system's {found.binary}{seccomp_note(found)})",
        lambda cmd, t: uml.run(found, cmd, t, mem),
    )


def find_uml_testing(mem: str, cache: Path) -> Kernel:
    found = uml.testing_uml(cache / "uml-testing")
    return Kernel(
        "uml-testing",
        f"user-mode Linux {found.version} (Debian testing{seccomp_note(found)}, "
        f"cached in {cache / 'uml-testing'})",
        lambda cmd, t: uml.run(found, cmd, t, mem),
    )


def find_qemu(mem: str, cache: Path) -> Kernel:
    found, version = qemu.qemu_kernel(cache / "qemu")
    return Kernel(
        "qemu",
        f"QEMU {version} with Debian's kernel {found.version} (cached in {cache / 'qemu'})",
        lambda cmd, t: qemu.run(found, cmd, t, mem),
        qemu.SLOW_NOTE,
    )


def finders(mem: str, cache: Path) -> dict[str, Callable[[], Kernel]]:
    return {
        "native": find_native,
        "uml-system": partial(find_uml_system, mem),
        "uml-testing": partial(find_uml_testing, mem, cache),
        "qemu": partial(find_qemu, mem, cache),
    }
