"""User-mode Linux: the system's (package ``user-mode-linux``), or Debian testing's,
fetched, unpacked next to its own libc, patchelf'ed and cached.

UML is an ordinary process with CAN and vcan modules; it mounts the host's root file
system through hostfs, so the guest runs this very checkout and virtualenv. Bookworm's
6.1um and trixie's 6.12um panic at init on CPUs with AMX (a larger XSAVE area than they
hand to ptrace); testing's 7.2 boots there. It needs glibc >= 2.38, newer than
bookworm's, hence testing's libc6 beside it (running it through the extracted ld-linux
instead of patching the interpreter makes UML miscompute its memory layout).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from . import apt
from .common import (
    PROBE_TIMEOUT_S,
    WayFailed,
    boot,
    finish_guest_run,
    log,
    missing_guest_tools,
    precompile,
    probe_verdict,
    write_init,
    write_probe_init,
)

SYSTEM_UML = Path("/usr/bin/linux.uml")
SYSTEM_MODULES = Path("/usr/lib/uml/modules")
TESTING_SUITE = "forky"  # Debian testing now; the unpinned package names follow it
TESTING_PACKAGES = ("user-mode-linux", "libc6")
LIBDIR = "usr/lib/x86_64-linux-gnu"
KEEP_MODULES = ("net/can", "drivers/net/can")  # all the guest loads; the rest is ~160 MB
PROBE_MEM = "256M"


# A kernel that has this message parses ``seccomp=``: UML's seccomp mode (Linux 6.16 and
# later), where a guest's system call is a seccomp trap in the host instead of a ptrace
# stop. In the HIL guest every time.monotonic() is such a call (UML has no vDSO): measured
# here, 127 us with bookworm's 6.1 and 60 us with testing's 7.2 under seccomp=auto.
SECCOMP_OPTION_MESSAGE = b"Invalid seccomp option '%s', expected on/auto/off"


@dataclass(frozen=True)
class Uml:
    binary: Path
    modules: Path  # <modules root>/<version>/kernel
    version: str
    seccomp: bool = False  # boots with seccomp=auto (falls back to ptrace where it cannot)


def knows_seccomp(binary: Path) -> bool:
    try:
        return SECCOMP_OPTION_MESSAGE in binary.read_bytes()
    except OSError:
        return False


def find_modules(binary: Path, modules_root: Path) -> Uml:
    """The kernel version of ``binary`` (``--version``), which names its module dir."""
    try:
        out = subprocess.run(
            [str(binary), "--version"], capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError) as exc:
        raise WayFailed(f"{binary} --version failed: {exc}") from exc
    version = out.stdout.strip()
    if out.returncode != 0 or not version:
        err = (out.stderr.strip().splitlines() or [f"exit {out.returncode}"])[-1]
        raise WayFailed(f"{binary} --version failed: {err[:160]}")
    if not (modules_root / version).is_dir():
        found = sorted(p.name for p in modules_root.glob("*") if p.is_dir())
        if len(found) != 1:
            raise WayFailed(f"no module dir for UML kernel {version!r} in {modules_root}")
        version = found[0]
    return Uml(binary, modules_root / version / "kernel", version, knows_seccomp(binary))


def uml_argv(uml: Uml, init: Path, work: Path, mem: str) -> list[str]:
    return [
        str(uml.binary),
        f"mem={mem}",
        "rootfstype=hostfs",
        "rw",
        f"init={init}",
        f"uml_dir={work}",
        "con=null",
        "con0=null,fd:1",
        *(["seccomp=auto"] if uml.seccomp else []),
    ]


def check_guest_tools() -> None:
    missing = missing_guest_tools()
    if missing:
        raise WayFailed(f"{' and '.join(missing)} missing for the guest (make debian-deps)")


def probe(uml: Uml, timeout_s: float = PROBE_TIMEOUT_S) -> None:
    """Boot ``uml`` with a tiny init that brings vcan0 up; raise WayFailed if it does not."""
    with tempfile.TemporaryDirectory(prefix="vcan-probe-") as tmp:
        work = Path(tmp)
        init = write_probe_init(work, uml.modules)
        rc, timed_out = boot(uml_argv(uml, init, work, PROBE_MEM), work, timeout_s)
        probe_verdict(work, rc, timed_out, timeout_s)


def run(uml: Uml, cmd: list[str], timeout_s: float, mem: str) -> int:
    precompile(cmd[0])
    with tempfile.TemporaryDirectory(prefix="vcan-uml-") as tmp:
        work = Path(tmp)
        init = write_init(work, cmd, uml.modules)
        rc, timed_out = boot(uml_argv(uml, init, work, mem), work, timeout_s, work / "pytest.out")
        return finish_guest_run(work, rc, timed_out, "user-mode Linux", timeout_s)


def system_uml() -> Uml:
    """The system's ``/usr/bin/linux.uml``, if it boots here with vcan."""
    if not os.access(SYSTEM_UML, os.X_OK):
        raise WayFailed(f"{SYSTEM_UML} not installed (make debian-deps)")
    check_guest_tools()
    uml = find_modules(SYSTEM_UML, SYSTEM_MODULES)
    probe(uml)
    return uml


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    """One fetch at a time per cache (two test runs may start together)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _cached(cache: Path) -> Uml:
    return find_modules(cache / "linux.uml", cache / "modules")


def _build(cache: Path) -> str:
    """Fetch testing's UML and libc into ``cache`` (replacing what is there); return a
    line on what was fetched."""
    if shutil.which("patchelf") is None:
        raise WayFailed("patchelf not installed (make debian-deps)")
    parent = cache.parent
    parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{cache.name}-new-", dir=parent) as tmp:
        new = Path(tmp) / "uml"
        private = apt.PrivateApt(Path(tmp) / "apt", suite=TESTING_SUITE)
        debs = private.download(TESTING_PACKAGES, Path(tmp) / "debs")
        size_mb = sum(d.stat().st_size for d in debs) / 1e6
        root = new / "root"
        for deb in debs:
            apt.unpack(deb, root)
        modules_src = root / "usr/lib/uml/modules"
        for version_dir in modules_src.glob("*"):
            for rel in KEEP_MODULES:
                src = version_dir / "kernel" / rel
                if src.is_dir():
                    dst = new / "modules" / version_dir.name / "kernel" / rel
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    shutil.move(src, dst)
        shutil.rmtree(modules_src, ignore_errors=True)
        binary = new / "linux.uml"
        shutil.move(root / "usr/bin/linux.uml", binary)
        loader = root / LIBDIR / "ld-linux-x86-64.so.2"
        if not binary.is_file() or not loader.is_file():
            raise WayFailed("the testing packages lack linux.uml or ld-linux-x86-64.so.2")
        final_root = cache / "root"  # the paths patchelf writes are the final ones
        patch = [
            "patchelf",
            "--set-interpreter",
            str(final_root / LIBDIR / "ld-linux-x86-64.so.2"),
            "--set-rpath",
            str(final_root / LIBDIR),
            str(binary),
        ]
        done = subprocess.run(patch, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise WayFailed(f"patchelf failed: {done.stderr.strip()[:200]}")
        names = " ".join(d.name for d in debs)
        summary = f"fetched {names} ({size_mb:.1f} MB) from Debian {TESTING_SUITE}"
        (new / "fetched.txt").write_text(summary + "\n")
        if cache.exists():
            shutil.rmtree(cache)
        new.rename(cache)
    return summary


def testing_uml(cache: Path) -> Uml:
    """Debian testing's UML from ``cache``, fetched (again) when missing or broken."""
    check_guest_tools()
    with _locked(cache.parent / f"{cache.name}.lock"):
        if (cache / "fetched.txt").is_file():
            try:
                uml = _cached(cache)
                probe(uml)
                return uml
            except WayFailed as exc:
                log(f"cached user-mode Linux in {cache} failed ({exc}); fetching it again")
        log(f"fetching user-mode Linux from Debian testing ({TESTING_SUITE}) into {cache}")
        log(_build(cache))
        uml = _cached(cache)
        try:
            probe(uml)
        except WayFailed:
            shutil.rmtree(cache, ignore_errors=True)  # keep only kernels that passed
            raise
        return uml
