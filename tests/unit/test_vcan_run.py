"""The pure parts of tools/vcan_run.py: the mirror from the apt sources, the order in which
ways are tried (with injected probe results), the one-line failure, the initramfs bits.
Nothing here boots a kernel or touches the network."""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import pytest

from tools.vcan import apt, qemu, uml
from tools.vcan.common import PROBE_OK, Kernel, WayFailed, probe_verdict, pytest_command
from tools.vcan.ways import WAYS, NoWay, cache_dir, failure_line, order_for, select

BOOKWORM_DEB822 = """\
Types: deb
# http://snapshot.debian.org/archive/debian/20250520T000000Z
URIs: http://deb.debian.org/debian
Suites: bookworm bookworm-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
# http://snapshot.debian.org/archive/debian-security/20250520T000000Z
URIs: http://deb.debian.org/debian-security
Suites: bookworm-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
"""


def test_deb822_mirror_is_the_main_archive_with_its_keyring() -> None:
    sources = apt.parse_deb822(BOOKWORM_DEB822)
    assert [s.suites for s in sources] == [("bookworm", "bookworm-updates"), ("bookworm-security",)]
    mirror = apt.debian_mirror(sources)
    assert mirror == apt.Mirror(
        "http://deb.debian.org/debian", "/usr/share/keyrings/debian-archive-keyring.gpg"
    )


def test_security_first_and_disabled_entries_are_passed_over() -> None:
    text = """\
Types: deb
URIs: http://security.debian.org/debian-security
Suites: bookworm-security
Components: main

Types: deb
URIs: http://old.example/debian
Suites: bookworm
Components: main
Enabled: no

Types: deb-src
URIs: http://src.example/debian
Suites: bookworm
Components: main

Types: deb
URIs: http://ftp.de.debian.org/debian/
Suites: bookworm
Components: main contrib
"""
    assert apt.debian_mirror(apt.parse_deb822(text)) == apt.Mirror(
        "http://ftp.de.debian.org/debian"
    )


def test_inline_signed_by_key_is_kept_whole() -> None:
    text = """\
Types: deb
URIs: https://mirror.example/debian
Suites: bookworm
Components: main
Signed-By:
 -----BEGIN PGP PUBLIC KEY BLOCK-----
 .
 mQINBGPL0BUBEADmW5NdOOHwPIJlgPu6JDcKw/NZJPR8lsD9K7UgrDeCkL4W0jGR
 -----END PGP PUBLIC KEY BLOCK-----
"""
    mirror = apt.debian_mirror(apt.parse_deb822(text))
    assert mirror.uri == "https://mirror.example/debian"
    assert mirror.signed_by.splitlines() == [
        "-----BEGIN PGP PUBLIC KEY BLOCK-----",
        "",
        "mQINBGPL0BUBEADmW5NdOOHwPIJlgPu6JDcKw/NZJPR8lsD9K7UgrDeCkL4W0jGR",
        "-----END PGP PUBLIC KEY BLOCK-----",
    ]


def test_one_line_sources_with_options_and_comments() -> None:
    text = """\
# deb http://commented.example/debian bookworm main
deb-src http://deb.debian.org/debian bookworm main
deb [arch=amd64 signed-by=/etc/apt/keyrings/d.gpg] http://m.example/debian bookworm main  # ours
deb http://security.debian.org/debian-security bookworm-security main
"""
    sources = apt.parse_one_line(text)
    assert len(sources) == 3
    assert apt.debian_mirror(sources) == apt.Mirror(
        "http://m.example/debian", "/etc/apt/keyrings/d.gpg"
    )


def test_a_live_mirror_wins_over_a_snapshot() -> None:
    text = """\
deb http://snapshot.debian.org/archive/debian/20250520T000000Z bookworm main
deb http://deb.debian.org/debian bookworm main
"""
    assert apt.debian_mirror(apt.parse_one_line(text)).uri == "http://deb.debian.org/debian"


def test_no_debian_archive_says_so() -> None:
    only_security = "deb http://security.debian.org/debian-security bookworm-security main\n"
    with pytest.raises(WayFailed, match="no Debian archive"):
        apt.debian_mirror(apt.parse_one_line(only_security))


def test_system_sources_reads_both_formats(tmp_path: Path) -> None:
    (tmp_path / "sources.list").write_text("deb http://a.example/debian bookworm main\n")
    parts = tmp_path / "sources.list.d"
    parts.mkdir()
    (parts / "debian.sources").write_text(BOOKWORM_DEB822)
    (parts / "other.list.disabled-by-farm").write_text("deb http://x.example/debian sid main\n")
    uris = [s.uris[0] for s in apt.system_sources(tmp_path)]
    assert uris == [
        "http://a.example/debian",
        "http://deb.debian.org/debian",
        "http://deb.debian.org/debian-security",
    ]


def test_private_sources_line_names_only_the_suite() -> None:
    mirror = apt.Mirror("http://deb.debian.org/debian", "/k.gpg")
    line = apt.private_sources_line(mirror, "forky", "[signed-by=/k.gpg] ")
    assert line == "deb [signed-by=/k.gpg] http://deb.debian.org/debian forky main\n"


def test_apt_options_keep_apt_state_private(tmp_path: Path) -> None:
    opts = apt.apt_options(tmp_path, tmp_path / "sources.list")
    pairs = dict(o.split("=", 1) for o in opts[1::2])
    assert opts[::2] == ["-o"] * len(pairs)
    assert pairs["Dir::State::Lists"] == str(tmp_path / "lists")
    assert pairs["Dir::Cache"] == str(tmp_path / "cache")
    assert pairs["Dir::Etc::sourcelist"] == str(tmp_path / "sources.list")
    assert pairs["Dir::Etc::sourceparts"] == "-"
    assert pairs["Dir::State::status"] == "/dev/null"


# --- choosing a way ---


def kernel(way: str) -> Kernel:
    return Kernel(way, f"{way} kernel", lambda cmd, timeout_s: 0)


def finder(way: str, failure: str | None, calls: list[str]) -> Callable[[], Kernel]:
    def find() -> Kernel:
        calls.append(way)
        if failure is not None:
            raise WayFailed(failure)
        return kernel(way)

    return find


def test_auto_tries_the_ways_in_order_and_takes_the_first_that_works() -> None:
    calls: list[str] = []
    results = {"native": "no SocketCAN", "uml-testing": "apt-get update failed", "uml-system": None}
    finders = {w: finder(w, results.get(w), calls) for w in WAYS}
    assert select(order_for("auto"), finders).way == "uml-system"
    assert calls == ["native", "uml-testing", "uml-system"]  # qemu never asked


def test_native_first_when_the_host_has_can() -> None:
    calls: list[str] = []
    finders = {w: finder(w, None, calls) for w in WAYS}
    assert select(order_for("auto"), finders).way == "native"
    assert calls == ["native"]


def test_a_forced_way_is_the_only_one_tried() -> None:
    calls: list[str] = []
    finders = {w: finder(w, None, calls) for w in WAYS}
    assert select(order_for("qemu"), finders).way == "qemu"
    assert calls == ["qemu"]
    calls.clear()
    finders["uml-testing"] = finder("uml-testing", "apt-get update failed", calls)
    with pytest.raises(NoWay) as err:
        select(order_for("uml-testing"), finders)
    assert calls == ["uml-testing"]
    assert err.value.failures == [("uml-testing", "apt-get update failed")]


def test_order_is_native_testing_uml_system_uml_qemu() -> None:
    assert order_for("auto") == ("native", "uml-testing", "uml-system", "qemu")


def test_seccomp_mode_is_asked_for_only_where_the_kernel_parses_it(tmp_path: Path) -> None:
    new, old = tmp_path / "linux-7.2.uml", tmp_path / "linux-6.1.uml"
    new.write_bytes(b"\x7fELF..." + uml.SECCOMP_OPTION_MESSAGE + b"...")
    old.write_bytes(b"\x7fELF... no such option ...")
    assert uml.knows_seccomp(new) and not uml.knows_seccomp(old)
    assert not uml.knows_seccomp(tmp_path / "missing")
    args = {
        binary.name: uml.uml_argv(
            uml.Uml(binary, tmp_path, "v", uml.knows_seccomp(binary)), tmp_path, tmp_path, "1G"
        )
        for binary in (new, old)
    }
    assert "seccomp=auto" in args[new.name]
    assert not any(a.startswith("seccomp") for a in args[old.name])


def test_when_nothing_works_one_line_names_every_way_and_why() -> None:
    calls: list[str] = []
    why = {
        "native": "host kernel 6.18 has no SocketCAN ([Errno 97] ...)",
        "uml-system": "probe boot: init never ran (exit 0: Kernel panic - not syncing:\n x)",
        "uml-testing": "apt-get update failed: E: network down",
        "qemu": "qemu-system-x86_64 not installed (make debian-deps)",
    }
    finders = {w: finder(w, why[w], calls) for w in WAYS}
    with pytest.raises(NoWay) as err:
        select(order_for("auto"), finders)
    line = str(err.value)
    assert calls == list(WAYS)
    assert "\n" not in line
    assert line.startswith("vcan_run: no kernel with SocketCAN vcan found (")
    positions = [line.index(f"{w}: ") for w in WAYS]
    assert positions == sorted(positions)
    assert "Kernel panic - not syncing: x" in line
    assert "E: network down" in line


def test_an_unforeseen_error_fails_that_way_only() -> None:
    def full_disk() -> Kernel:
        raise OSError(28, "No space left on device")

    calls: list[str] = []
    finders = {w: finder(w, None, calls) for w in WAYS}
    finders["native"] = finder("native", "no SocketCAN", calls)
    finders["uml-system"] = full_disk
    assert select(order_for("auto"), finders).way == "uml-testing"
    with pytest.raises(NoWay, match=r"uml-system: OSError: \[Errno 28\] No space left"):
        select(("uml-system",), finders)


def test_failure_line_format() -> None:
    assert failure_line([("native", "no CAN"), ("qemu", "not installed")]) == (
        "vcan_run: no kernel with SocketCAN vcan found (native: no CAN; qemu: not installed)"
    )


def test_cache_dir_follows_xdg() -> None:
    assert cache_dir({"XDG_CACHE_HOME": "/x", "HOME": "/h"}) == Path("/x/dbw-applique/vcan")
    assert cache_dir({"HOME": "/h"}) == Path("/h/.cache/dbw-applique/vcan")
    assert cache_dir({"XDG_CACHE_HOME": "", "HOME": "/h"}) == Path("/h/.cache/dbw-applique/vcan")


def test_pytest_command_adds_the_vcan_marker_unless_given() -> None:
    assert pytest_command("py", []) == ["py", "-m", "pytest", "-m", "vcan", "tests/hil", "-v"]
    assert pytest_command("py", ["-m", "not slow", "x"]) == [
        "py",
        "-m",
        "pytest",
        "-m",
        "not slow",
        "x",
    ]


# --- QEMU's initramfs ---


def test_module_load_order_puts_dependencies_first() -> None:
    depends = {
        "virtio_ring": [],
        "virtio": ["virtio_ring"],
        "virtio_pci_modern_dev": [],
        "virtio_pci_legacy_dev": [],
        "virtio_pci": ["virtio_ring", "virtio_pci_modern_dev", "virtio_pci_legacy_dev", "virtio"],
        "netfs": [],
        "fscache": ["netfs"],
        "9pnet": [],
        "9pnet_virtio": ["virtio", "9pnet", "virtio_ring"],
        "9p": ["9pnet", "fscache", "netfs"],
    }
    order = qemu.load_order(qemu.BOOT_MODULES, depends)
    assert sorted(order) == sorted(depends)
    for name, deps in depends.items():
        assert all(order.index(d) < order.index(name) for d in deps)
    with pytest.raises(WayFailed, match="not in the kernel package"):
        qemu.load_order(["9p"], {"9p": ["fscache"]})
    with pytest.raises(WayFailed, match="loop"):
        qemu.load_order(["a"], {"a": ["b"], "b": ["a"]})


def test_cpio_newc_members_are_aligned_and_end_with_a_trailer() -> None:
    entry = qemu.cpio_entry("init", 0o100755, b"#!/bin/sh\n")
    assert entry.startswith(b"070701")
    assert len(entry) % 4 == 0
    header = entry[6:110]
    fields = [int(header[i : i + 8], 16) for i in range(0, 104, 8)]
    assert fields[1] == 0o100755 and fields[6] == 10 and fields[11] == len("init") + 1
    assert entry[110:115] == b"init\0"
    console = qemu.cpio_entry("dev/console", 0o20600, rdev=(5, 1))
    assert [int(console[6 + 8 * i : 14 + 8 * i], 16) for i in (9, 10)] == [5, 1]
    archive = qemu.cpio_archive([entry])
    assert archive.endswith(qemu.cpio_entry("TRAILER!!!", 0))


def elf(interp: bool) -> bytes:
    phoff, phentsize = 64, 56
    types = [1, 3, 1] if interp else [1, 1]
    header = bytearray(b"\x7fELF\x02\x01\x01" + b"\0" * 57)
    struct.pack_into("<Q", header, 0x20, phoff)
    struct.pack_into("<HH", header, 0x36, phentsize, len(types))
    return bytes(header) + b"".join(struct.pack("<I", t) + b"\0" * 52 for t in types)


def test_static_elf_means_no_program_interpreter(tmp_path: Path) -> None:
    (tmp_path / "static").write_bytes(elf(interp=False))
    (tmp_path / "dynamic").write_bytes(elf(interp=True))
    (tmp_path / "script").write_bytes(b"#!/bin/sh\n" + b"\0" * 80)
    assert qemu.is_static_elf(tmp_path / "static")
    assert not qemu.is_static_elf(tmp_path / "dynamic")
    assert not qemu.is_static_elf(tmp_path / "script")


# --- reading a probe boot ---

AMX_PANIC_CONSOLE = """\
Linux version 6.1.176 ...
Run /tmp/vcan-probe-x/probe-init.sh as init process
Kernel panic - not syncing: Attempted to kill init! exitcode=0x0000000b
CPU: 0 PID: 1 Comm: probe-init.sh Not tainted 6.1.176
"""


def test_probe_verdict_passes_when_vcan0_came_up(tmp_path: Path) -> None:
    (tmp_path / "probe.out").write_text(f"booted\n{PROBE_OK}\n")
    probe_verdict(tmp_path, 0, False, 20.0)


def test_probe_verdict_names_the_panic(tmp_path: Path) -> None:
    (tmp_path / "console.log").write_text(AMX_PANIC_CONSOLE)
    with pytest.raises(WayFailed) as err:
        probe_verdict(tmp_path, 1, False, 20.0)
    assert str(err.value) == (
        "probe boot: init never ran (exit 1: "
        "Kernel panic - not syncing: Attempted to kill init! exitcode=0x0000000b)"
    )


def test_probe_verdict_on_a_hang_and_on_a_missing_module(tmp_path: Path) -> None:
    (tmp_path / "console.log").write_text("Linux version 7.2.7\nhostfs: mounted\n")
    with pytest.raises(WayFailed, match=r"timed out after 20 s \(hostfs: mounted\)"):
        probe_verdict(tmp_path, -9, True, 20.0)
    (tmp_path / "probe.out").write_text("booted\n")
    (tmp_path / "setup.log").write_text("insmod net/can/can.ko failed\nUnknown device type\n")
    with pytest.raises(WayFailed, match=r"vcan0 did not come up .*can\.ko failed; Unknown device"):
        probe_verdict(tmp_path, 0, False, 20.0)
