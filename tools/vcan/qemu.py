"""QEMU with Debian bookworm's own kernel: the slow last resort.

The kernel package (whatever ``linux-image-amd64`` depends on in the system's own
sources) is fetched with ``apt-get download`` through private apt state and unpacked
with ``dpkg-deb -x``; a busybox-static initramfs loads the virtio, netfs, fscache and 9p
modules, mounts the host's ``/`` over virtio-9p and ``switch_root``s into the same kind
of init script the UML guest runs. KVM does not work on these machines (nested
virtualisation: the guest hangs at kernel start), so it runs under TCG, where Python is
about 11x slower; ``-cpu max`` because a compiled wheel dies with "Illegal instruction"
on QEMU's default CPU model.
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import struct
import subprocess
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from . import apt
from .common import (
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

QEMU = "qemu-system-x86_64"
BUSYBOX = Path("/bin/busybox")
KERNEL_META = "linux-image-amd64"
# Loaded by the initramfs before the host's / can be mounted; their dependencies
# (modinfo's "depends") are loaded first.
BOOT_MODULES = ("virtio_pci", "9pnet_virtio", "9p")
KEEP_MODULE_DIRS = (
    "drivers/virtio",
    "fs/9p",
    "fs/netfs",
    "fs/fscache",
    "net/9p",
    "net/can",
    "drivers/net/can",
)
ROOT_TAG = "hostroot"
WORK_TAG = "vcanwork"
QEMU_PROBE_TIMEOUT_S = 90.0  # the probe boot took 32 s here with the 2 cores busy
SLOW_NOTE = (
    "slow: QEMU emulates the CPU (TCG, no KVM here), Python runs about 11x slower, "
    "so timing-sensitive tests may fail on time alone"
)


@dataclass(frozen=True)
class QemuKernel:
    vmlinuz: Path
    initramfs: Path
    modules: Path  # <cache>/modules/<version>/kernel
    version: str


# --- initramfs (cpio "newc"), written here so that no cpio tool is needed ---


def cpio_entry(name: str, mode: int, data: bytes = b"", rdev: tuple[int, int] = (0, 0)) -> bytes:
    """One member of a newc cpio archive (``mode`` includes the file type bits)."""
    fields = (
        0,  # ino
        mode,
        0,  # uid
        0,  # gid
        1,  # nlink
        0,  # mtime
        len(data),
        0,  # devmajor
        0,  # devminor
        rdev[0],
        rdev[1],
        len(name) + 1,
        0,  # check
    )
    header = b"070701" + b"".join(b"%08X" % f for f in fields)
    out = header + name.encode() + b"\0"
    out += b"\0" * (-len(out) % 4)
    out += data + b"\0" * (-len(data) % 4)
    return out


def cpio_archive(entries: Iterable[bytes]) -> bytes:
    return b"".join([*entries, cpio_entry("TRAILER!!!", 0)])


def is_static_elf(path: Path) -> bool:
    """True for an ELF executable without a program interpreter (PT_INTERP)."""
    data = path.read_bytes()
    if data[:4] != b"\x7fELF" or data[4] != 2:  # 64-bit only
        return False
    (phoff,) = struct.unpack_from("<Q", data, 0x20)
    phentsize, phnum = struct.unpack_from("<HH", data, 0x36)
    types = (struct.unpack_from("<I", data, phoff + i * phentsize)[0] for i in range(phnum))
    return 3 not in types


def load_order(wanted: Sequence[str], depends: dict[str, list[str]]) -> list[str]:
    """``wanted`` modules and what they depend on, dependencies first."""
    order: list[str] = []

    def visit(name: str, path: tuple[str, ...]) -> None:
        if name in order:
            return
        if name in path:
            raise WayFailed(f"module dependency loop: {' -> '.join((*path, name))}")
        if name not in depends:
            raise WayFailed(f"module {name} not in the kernel package")
        for dep in depends[name]:
            visit(dep, (*path, name))
        order.append(name)

    for name in wanted:
        visit(name, ())
    return order


def module_depends(kernel_dir: Path) -> tuple[dict[str, list[str]], dict[str, Path]]:
    """Each module's name -> its "depends" (modinfo), and name -> file."""
    files = {p.name.split(".ko")[0]: p for p in kernel_dir.rglob("*.ko*")}
    modinfo = shutil.which("modinfo") or shutil.which("modinfo", path="/sbin:/usr/sbin")
    if modinfo is None:
        raise WayFailed("modinfo missing (package kmod; make debian-deps)")
    depends = {}
    for name, path in files.items():
        done = subprocess.run(
            [modinfo, "-F", "depends", str(path)], capture_output=True, text=True, check=False
        )
        depends[name] = [d for d in done.stdout.strip().split(",") if d]
    return depends, files


def initramfs_init(modules: Sequence[str]) -> str:
    """The initramfs's /init: the host's / over 9p with the page cache on (Python's
    imports were 4x slower without it), the run's work folder (``vcanwork=`` on the
    kernel command line) over its own uncached 9p so that the host sees the guest's
    output as it is written, then ``switch_root`` to ``vcaninit=``."""
    bb = "/bin/busybox"
    opts = "trans=virtio,version=9p2000.L,msize=512000"
    insmods = "\n".join(f"{bb} insmod /modules/{m}.ko || echo 'insmod {m} failed'" for m in modules)
    return f"""#!{bb} sh
# Generated by tools/vcan_run.py: mount the host's / over virtio-9p, switch_root into it.
{bb} mkdir -p /proc /sys /dev /newroot
{bb} mount -t devtmpfs devtmpfs /dev
{insmods}
if ! {bb} mount -t 9p -o {opts},cache=loose {ROOT_TAG} /newroot ||
   ! {bb} mount -t 9p -o {opts} {WORK_TAG} "/newroot$vcanwork"; then
  echo "vcan-initramfs: cannot mount the host's files over 9p"; {bb} poweroff -f
fi
{bb} mount --move /dev /newroot/dev
exec {bb} switch_root /newroot "$vcaninit"
"""


def build_initramfs(dest: Path, kernel_dir: Path) -> None:
    if not BUSYBOX.is_file() or not is_static_elf(BUSYBOX):
        raise WayFailed(f"no static {BUSYBOX} (package busybox-static; make debian-deps)")
    depends, files = module_depends(kernel_dir)
    order = load_order(BOOT_MODULES, depends)
    entries = [
        cpio_entry("bin", 0o40755),
        cpio_entry("dev", 0o40755),
        cpio_entry("dev/console", 0o20600, rdev=(5, 1)),
        cpio_entry("modules", 0o40755),
        cpio_entry("bin/busybox", 0o100755, BUSYBOX.read_bytes()),
        cpio_entry("init", 0o100755, initramfs_init(order).encode()),
    ]
    for name in order:
        if files[name].suffix != ".ko":
            raise WayFailed(f"module {files[name].name} is compressed; busybox cannot load it")
        entries.append(cpio_entry(f"modules/{name}.ko", 0o100644, files[name].read_bytes()))
    dest.write_bytes(cpio_archive(entries))


# --- fetching and caching the kernel ---


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _cached(cache: Path) -> QemuKernel:
    """The cached kernel, with an initramfs built anew (cheap; it follows this code)."""
    found = sorted(p.name for p in (cache / "modules").glob("*") if p.is_dir())
    if len(found) != 1 or not (cache / "vmlinuz").is_file():
        raise WayFailed(f"broken cache in {cache}")
    fresh = cache / f".initramfs-{os.getpid()}.cpio"
    build_initramfs(fresh, cache / "modules" / found[0] / "kernel")
    fresh.rename(cache / "initramfs.cpio")  # atomic: a QEMU starting now reads one whole
    return QemuKernel(
        cache / "vmlinuz",
        cache / "initramfs.cpio",
        cache / "modules" / found[0] / "kernel",
        found[0],
    )


def _build(cache: Path) -> str:
    parent = cache.parent
    parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{cache.name}-new-", dir=parent) as tmp:
        work = Path(tmp)
        private = apt.PrivateApt(work / "apt")  # the system's own sources: bookworm
        image = [d for d in private.depends(KERNEL_META) if d.startswith("linux-image-")]
        if not image:
            raise WayFailed(f"{KERNEL_META} depends on no linux-image package")
        debs = private.download(image[:1], work / "debs")
        size_mb = debs[0].stat().st_size / 1e6
        root = work / "root"
        apt.unpack(debs[0], root)
        new = work / "qemu"
        new.mkdir()
        vmlinuz = sorted((root / "boot").glob("vmlinuz-*"))
        versions = sorted(p.name for p in (root / "lib/modules").glob("*") if p.is_dir())
        if len(vmlinuz) != 1 or len(versions) != 1:
            raise WayFailed(f"unexpected layout in {debs[0].name}")
        shutil.move(vmlinuz[0], new / "vmlinuz")
        for rel in KEEP_MODULE_DIRS:
            src = root / "lib/modules" / versions[0] / "kernel" / rel
            if src.is_dir():
                dst = new / "modules" / versions[0] / "kernel" / rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(src, dst)
        summary = f"fetched {debs[0].name} ({size_mb:.1f} MB) from the system's Debian sources"
        (new / "fetched.txt").write_text(summary + "\n")
        if cache.exists():
            shutil.rmtree(cache)
        new.rename(cache)
    return summary


# --- booting ---


def qemu_argv(k: QemuKernel, init: Path, mem: str) -> list[str]:
    """The guest sees the host's / and, uncached, ``init``'s folder (the run's work)."""
    security = "passthrough" if os.geteuid() == 0 else "none"
    work = init.parent
    fsdevs = []
    for n, (path, tag) in enumerate(((Path("/"), ROOT_TAG), (work, WORK_TAG))):
        fsdevs += [
            "-fsdev",
            f"local,id=fs{n},path={path},security_model={security},multidevs=remap",
            "-device",
            f"virtio-9p-pci,fsdev=fs{n},mount_tag={tag}",
        ]
    return [
        QEMU,
        "-nodefaults",
        "-no-reboot",
        "-display",
        "none",
        "-monitor",
        "none",
        "-serial",
        "stdio",
        "-accel",
        "tcg,thread=multi",
        "-cpu",
        "max",
        "-smp",
        str(min(os.cpu_count() or 1, 4)),
        "-m",
        mem,
        "-kernel",
        str(k.vmlinuz),
        "-initrd",
        str(k.initramfs),
        "-append",
        f"console=ttyS0 panic=-1 loglevel=4 vcaninit={init} vcanwork={work}",
        *fsdevs,
    ]


def qemu_version() -> str:
    try:
        out = subprocess.run([QEMU, "--version"], capture_output=True, text=True, check=False)
    except OSError as exc:
        raise WayFailed(f"{QEMU} not installed (make debian-deps)") from exc
    m = re.search(r"version (\S+)", out.stdout)
    return m.group(1) if m else "?"


def probe(k: QemuKernel, timeout_s: float = QEMU_PROBE_TIMEOUT_S) -> None:
    with tempfile.TemporaryDirectory(prefix="vcan-qemu-probe-") as tmp:
        work = Path(tmp)
        init = write_probe_init(work, k.modules)
        rc, timed_out = boot(qemu_argv(k, init, "512M"), work, timeout_s)
        probe_verdict(work, rc, timed_out, timeout_s)


def run(k: QemuKernel, cmd: list[str], timeout_s: float, mem: str) -> int:
    precompile(cmd[0])
    with tempfile.TemporaryDirectory(prefix="vcan-qemu-") as tmp:
        work = Path(tmp)
        init = write_init(work, cmd, k.modules)
        rc, timed_out = boot(qemu_argv(k, init, mem), work, timeout_s, work / "pytest.out")
        return finish_guest_run(work, rc, timed_out, "QEMU", timeout_s)


def qemu_kernel(cache: Path) -> tuple[QemuKernel, str]:
    """Bookworm's kernel for QEMU from ``cache`` (fetched again when missing or broken),
    probed; and QEMU's version."""
    version = qemu_version()
    missing = missing_guest_tools()
    if missing:
        raise WayFailed(f"{' and '.join(missing)} missing for the guest (make debian-deps)")
    if not BUSYBOX.is_file() or not is_static_elf(BUSYBOX):
        raise WayFailed(f"no static {BUSYBOX} (package busybox-static; make debian-deps)")
    with _locked(cache.parent / f"{cache.name}.lock"):
        if (cache / "fetched.txt").is_file():
            try:
                k = _cached(cache)
                probe(k)
                return k, version
            except WayFailed as exc:
                log(f"cached QEMU kernel in {cache} failed ({exc}); fetching it again")
        log(f"fetching Debian's kernel for QEMU into {cache}")
        log(_build(cache))
        k = _cached(cache)
        try:
            probe(k)
        except WayFailed:
            shutil.rmtree(cache, ignore_errors=True)
            raise
        return k, version
