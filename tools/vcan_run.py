#!/usr/bin/env python3
"""Run the ``vcan``-marked hardware-in-the-loop tests against a real SocketCAN vcan0.

Why this exists: the HIL tests need kernel SocketCAN, but the development and CI
machines run kernels without CAN (socket(AF_CAN) fails with errno 97). When the host
can do vcan, pytest runs natively. Otherwise this boots Debian's user-mode Linux
kernel (``linux.uml``, an ordinary process with CAN and vcan modules) with the host's
root file system mounted through hostfs, so the guest runs this very checkout and
virtualenv; the test output and exit status come back through files on the host
(the guest's own exit status says nothing about the tests). The recipe is the one in
/work/shared/notes/vcan-without-kernel-support.md.

Usage: tools/vcan_run.py [--mode auto|native|uml] [--timeout-s N] [pytest args...]
Unknown arguments (or everything after ``--``) go to pytest. ``-m vcan`` is added
unless a ``-m`` is given, because pyproject's addopts deselect vcan tests by default
(a later ``-m`` on the command line wins over addopts).
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_PYTEST_ARGS = ["tests/hil", "-v"]
UML_KERNEL = "/usr/bin/linux.uml"
UML_MODULES = Path("/usr/lib/uml/modules")
# Load order matters: protocols need can.ko, the vcan/vxcan drivers need can-dev.ko.
CAN_MODULES = (
    "net/can/can.ko",
    "net/can/can-raw.ko",
    "net/can/can-bcm.ko",
    "net/can/can-gw.ko",
    "drivers/net/can/dev/can-dev.ko",
    "drivers/net/can/vcan.ko",
    "drivers/net/can/vxcan.ko",
)
GUEST_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
PASS_ENV = ("CI", "NO_COLOR", "FORCE_COLOR", "PY_COLORS")
PASS_ENV_PREFIXES = ("PYTEST_", "HYPOTHESIS_")
PRECOMPILE_DIRS = ("appliance", "drivers", "safety", "calibration", "tools", "tests")
EXIT_TIMEOUT = 124  # like timeout(1)
EXIT_RUNNER_FAILURE = 125  # the runner could not get a pytest status at all
APT_HINT = "apt-get install -y user-mode-linux kmod can-utils iproute2"


def pytest_command(python: str, args: list[str]) -> list[str]:
    """The pytest command line; adds ``-m vcan`` (overriding addopts) unless one is given."""
    args = args or DEFAULT_PYTEST_ARGS
    has_marker = any(a == "-m" or (a.startswith("-m") and not a.startswith("--")) for a in args)
    return [python, "-m", "pytest", *([] if has_marker else ["-m", "vcan"]), *args]


def native_vcan() -> bool:
    """True when this kernel has SocketCAN and vcan0 exists (or could be created) and is up."""
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (AttributeError, OSError):
        return False
    ip = shutil.which("ip")
    if ip is None:
        return Path("/sys/class/net/vcan0").exists()
    if not Path("/sys/class/net/vcan0").exists():
        add = [ip, "link", "add", "dev", "vcan0", "type", "vcan"]
        if subprocess.run(add, capture_output=True, check=False).returncode != 0:
            return False
    up = subprocess.run([ip, "link", "set", "up", "vcan0"], capture_output=True, check=False)
    return up.returncode == 0


def run_native(cmd: list[str], timeout_s: float) -> int:
    print("vcan: native", flush=True)
    try:
        return subprocess.run(cmd, cwd=PROJECT_ROOT, timeout=timeout_s, check=False).returncode
    except subprocess.TimeoutExpired:
        print(f"vcan_run: pytest timed out after {timeout_s:.0f} s", file=sys.stderr)
        return EXIT_TIMEOUT


def uml_version() -> str:
    """The kernel version of linux.uml, which names its module directory."""
    out = subprocess.run([UML_KERNEL, "--version"], capture_output=True, text=True, timeout=30)
    version = out.stdout.strip()
    if not (UML_MODULES / version).is_dir():
        found = sorted(p.name for p in UML_MODULES.glob("*") if p.is_dir())
        if len(found) != 1:
            raise RuntimeError(f"no module dir for UML kernel {version!r} in {UML_MODULES}")
        version = found[0]
    return version


def guest_env(tmp_dir: Path) -> dict[str, str]:
    """The environment pytest sees in the guest (init starts with almost nothing)."""
    env = {
        "PATH": GUEST_PATH,
        "HOME": os.environ.get("HOME", "/root"),
        "LANG": "C.UTF-8",
        "TMPDIR": str(tmp_dir),
        "PYTHONDONTWRITEBYTECODE": "1",  # the guest should not litter the tree with .pyc
        "COLUMNS": str(shutil.get_terminal_size().columns),
    }
    if sys.stdout.isatty():
        env["PY_COLORS"] = "1"
    for name, value in os.environ.items():
        if name in PASS_ENV or name.startswith(PASS_ENV_PREFIXES):
            env[name] = value
    return env


def write_init(work: Path, cmd: list[str], modules: Path) -> Path:
    """Write the guest's PID 1: set up CAN, run pytest, record its status, power off."""
    q = shlex.quote
    tmp_dir = work / "tmp"
    tmp_dir.mkdir()
    env = " ".join(q(f"{k}={v}") for k, v in guest_env(tmp_dir).items())
    insmods = "\n".join(
        f"insmod {q(str(modules / m))} || echo 'insmod {m} failed'" for m in CAN_MODULES
    )
    script = f"""#!/bin/sh
# Generated by tools/vcan_run.py: PID 1 of a user-mode Linux guest on hostfs.
export PATH={GUEST_PATH}
{{
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mkdir -p /dev/shm && mount -t tmpfs -o mode=1777 tmpfs /dev/shm
# /dev is the guest's own devtmpfs (not the host's): give it the pseudo-terminals the
# simulated serial boards run on.
mkdir -p /dev/pts && mount -t devpts -o ptmxmode=0666,mode=0620 devpts /dev/pts
mount -t tmpfs -o mode=1777 tmpfs {q(str(tmp_dir))}  # TMPDIR: guest-only, AF_UNIX-safe
{insmods}
ip link set lo up
ip link add dev vcan0 type vcan && ip link set up vcan0
}} > {q(str(work / "setup.log"))} 2>&1
cd {q(str(PROJECT_ROOT))}
env -i {env} {" ".join(map(q, cmd))} > {q(str(work / "pytest.out"))} 2>&1 < /dev/null
echo $? > {q(str(work / "status"))}
sync
poweroff -f || echo o > /proc/sysrq-trigger
"""
    init = work / "init.sh"
    init.write_text(script)
    init.chmod(0o755)
    return init


def stream(path: Path, offset: int) -> int:
    """Copy what the guest appended to ``path`` since ``offset`` to our stdout."""
    try:
        with path.open("rb") as f:
            f.seek(offset)
            data = f.read()
    except FileNotFoundError:
        return offset
    sys.stdout.buffer.write(data)
    sys.stdout.flush()
    return offset + len(data)


def read_text(path: Path) -> str:
    """The text of a file the guest may or may not have written ("" if it did not)."""
    try:
        return path.read_text(errors="replace")
    except FileNotFoundError:
        return ""


def precompile(python: str) -> None:
    """Byte-compile the project on the host first: inside the guest every file access
    goes through hostfs and ptrace, and compiling modules there made a single import of
    the drivers take 15 s (this environment also sets PYTHONDONTWRITEBYTECODE, so
    nothing would be cached between processes)."""
    subprocess.run(
        [python, "-m", "compileall", "-q", "-j", "0", *PRECOMPILE_DIRS],
        cwd=PROJECT_ROOT,
        capture_output=True,
        check=False,
    )


def run_uml(cmd: list[str], timeout_s: float, mem: str) -> int:
    missing = [t for t in ("insmod", "ip") if shutil.which(t, path=GUEST_PATH) is None]
    if not os.access(UML_KERNEL, os.X_OK) or missing:
        need = [UML_KERNEL, *missing]
        print(f"vcan_run: no native vcan, and {need} missing: {APT_HINT}", file=sys.stderr)
        return EXIT_RUNNER_FAILURE
    try:
        version = uml_version()
    except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
        print(f"vcan_run: cannot use {UML_KERNEL}: {exc}", file=sys.stderr)
        return EXIT_RUNNER_FAILURE
    print(f"vcan: user-mode Linux {version}", flush=True)
    precompile(cmd[0])
    with tempfile.TemporaryDirectory(prefix="vcan-uml-") as tmp:
        work = Path(tmp)
        init = write_init(work, cmd, UML_MODULES / version / "kernel")
        console = work / "console.log"
        uml = [
            UML_KERNEL,
            f"mem={mem}",
            "rootfstype=hostfs",
            "rw",
            f"init={init}",
            f"uml_dir={work}",
            "con=null",
            "con0=null,fd:1",
        ]
        with console.open("wb") as log:
            proc = subprocess.Popen(
                uml,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=log,
                cwd=work,
                start_new_session=True,
            )
        deadline = time.monotonic() + timeout_s
        offset = 0
        try:
            while proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.2)
                offset = stream(work / "pytest.out", offset)
            timed_out = proc.poll() is None
        finally:  # on timeout and on Ctrl-C too: UML runs in its own session
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)  # its helper processes share the group
            proc.wait()
        stream(work / "pytest.out", offset)
        setup = read_text(work / "setup.log")
        if setup.strip():
            print(f"vcan_run: guest setup reported:\n{setup}", file=sys.stderr)
        status = read_text(work / "status").strip()
        if timed_out or not status.isdigit():
            why = f"timed out after {timeout_s:.0f} s" if timed_out else "left no pytest status"
            tail = read_text(console).splitlines()[-40:]
            print(
                f"vcan_run: user-mode Linux {why} (exit {proc.returncode}); console tail:",
                *tail,
                sep="\n",
                file=sys.stderr,
            )
            return EXIT_TIMEOUT if timed_out else EXIT_RUNNER_FAILURE
        return int(status)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    after_dashes = argv[argv.index("--") + 1 :] if "--" in argv else []
    ours = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        epilog=f"Other arguments, and all after --, go to pytest (default: "
        f"{' '.join(DEFAULT_PYTEST_ARGS)}); -m vcan is added unless a -m is given.",
        allow_abbrev=False,
    )
    parser.add_argument(
        "--mode",
        choices=("auto", "native", "uml"),
        default="auto",
        help="auto (default): native if the host has vcan, else UML",
    )
    parser.add_argument("--timeout-s", type=float, default=600.0, help="overall limit (600)")
    parser.add_argument("--mem", default="1G", help="user-mode Linux memory (1G)")
    opts, pytest_args = parser.parse_known_args(ours)
    cmd = pytest_command(os.path.abspath(sys.executable), pytest_args + after_dashes)
    start = time.monotonic()
    if opts.mode == "native" or (opts.mode == "auto" and native_vcan()):
        rc = run_native(cmd, opts.timeout_s)
    else:
        rc = run_uml(cmd, opts.timeout_s, opts.mem)
    print(f"vcan_run: exit status {rc} after {time.monotonic() - start:.1f} s", flush=True)
    return rc


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # run_uml has already killed the guest
        print("vcan_run: interrupted", file=sys.stderr)
        sys.exit(130)
