"""Fetching Debian packages without touching the system's apt state.

The system's apt sources name the mirror (and the keyring that signs it); a private
sources list, lists directory and cache (``-o Dir::...``) let ``apt-get update`` and
``apt-get download`` work for another suite, unprivileged and with signature checks,
while the system's sources, lists, caches and installed packages stay as they were.
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from .common import WayFailed

APT_ETC = Path("/etc/apt")
DEBIAN_KEYRING = Path("/usr/share/keyrings/debian-archive-keyring.gpg")


@dataclass(frozen=True)
class AptSource:
    """One entry of the system's apt sources (either format)."""

    types: tuple[str, ...]
    uris: tuple[str, ...]
    suites: tuple[str, ...]
    components: tuple[str, ...]
    signed_by: str = ""  # a keyring path, an inline key block, or "" (apt's defaults)
    enabled: bool = True


@dataclass(frozen=True)
class Mirror:
    """Where the system gets Debian from, and the keyring that signs it."""

    uri: str
    signed_by: str = ""


def _deb822_stanzas(text: str) -> Iterable[dict[str, str]]:
    fields: dict[str, str] = {}
    name = ""
    for raw in [*text.splitlines(), ""]:
        if raw.startswith("#"):
            continue
        if not raw.strip():
            if fields:
                yield fields
            fields, name = {}, ""
        elif raw[0] in " \t" and name:  # continuation; " ." stands for an empty line
            line = raw.strip()
            fields[name] += "\n" + ("" if line == "." else line)
        elif ":" in raw:
            key, _, value = raw.partition(":")
            name = key.strip().lower()
            fields[name] = value.strip()


def parse_deb822(text: str) -> list[AptSource]:
    """Entries of a ``.sources`` file (deb822 format)."""
    out = []
    for f in _deb822_stanzas(text):
        out.append(
            AptSource(
                types=tuple(f.get("types", "").split()),
                uris=tuple(f.get("uris", "").split()),
                suites=tuple(f.get("suites", "").split()),
                components=tuple(f.get("components", "").split()),
                signed_by=f.get("signed-by", "").strip(),
                enabled=f.get("enabled", "yes").strip().lower() not in ("no", "false", "0"),
            )
        )
    return out


_ONE_LINE = re.compile(r"^(deb|deb-src)\s+(?:\[([^\]]*)\]\s+)?(\S+)\s+(\S+)\s*(.*)$")


def parse_one_line(text: str) -> list[AptSource]:
    """Entries of a ``sources.list`` file (one-line format)."""
    out = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        m = _ONE_LINE.match(line)
        if not m:
            continue
        kind, options, uri, suite, components = m.groups()
        opts = dict(o.split("=", 1) for o in (options or "").split() if "=" in o)
        out.append(
            AptSource(
                types=(kind,),
                uris=(uri,),
                suites=(suite,),
                components=tuple(components.split()),
                signed_by=opts.get("signed-by", ""),
            )
        )
    return out


def system_sources(etc: Path = APT_ETC) -> list[AptSource]:
    """Every entry of the system's apt sources, in the order apt reads them."""
    out = []
    main_list = etc / "sources.list"
    if main_list.is_file():
        out += parse_one_line(main_list.read_text(errors="replace"))
    parts = etc / "sources.list.d"
    for path in sorted(parts.glob("*")) if parts.is_dir() else []:
        if path.suffix == ".list":
            out += parse_one_line(path.read_text(errors="replace"))
        elif path.suffix == ".sources":
            out += parse_deb822(path.read_text(errors="replace"))
    return out


def debian_mirror(sources: Sequence[AptSource]) -> Mirror:
    """The URI of the system's main Debian archive (not security, updates or backports),
    with the Signed-By it is used with. A live mirror wins over a snapshot one."""
    candidates = []
    for src in sources:
        if not src.enabled or "deb" not in src.types or "main" not in src.components:
            continue
        if not any(s and "-" not in s and "/" not in s for s in src.suites):
            continue  # e.g. only bookworm-security, bookworm-updates, or a flat repo
        for uri in src.uris:
            if "security" in uri or "/debian" not in uri.rstrip("/") + "/":
                continue
            candidates.append(Mirror(uri.rstrip("/"), src.signed_by))
    if not candidates:
        raise WayFailed("no Debian archive (suite with component main) in the apt sources")
    live = [m for m in candidates if "snapshot." not in m.uri]
    return (live or candidates)[0]


def _signed_by_option(mirror: Mirror, work: Path) -> str:
    """The ``[signed-by=...]`` of the private list: the system's own choice for this
    mirror, or Debian's archive keyring."""
    key = mirror.signed_by
    if "BEGIN PGP" in key:  # deb822 allows the key itself in the field
        keyring = work / "signed-by.asc"
        keyring.write_text(key.strip() + "\n")
        return f"[signed-by={keyring}] "
    if key:
        return f"[signed-by={key.split()[0]}] "
    if DEBIAN_KEYRING.is_file():
        return f"[signed-by={DEBIAN_KEYRING}] "
    return ""


def private_sources_line(mirror: Mirror, suite: str, signed_by: str) -> str:
    return f"deb {signed_by}{mirror.uri} {suite} main\n"


def apt_options(work: Path, sources_list: Path | None) -> list[str]:
    """apt-get options that keep every file apt reads or writes inside ``work``
    (``sources_list=None``: the system's own sources, with private lists)."""
    opts = [
        f"-o Dir::State::Lists={work / 'lists'}",
        f"-o Dir::Cache={work / 'cache'}",
        "-o Dir::State::status=/dev/null",  # what the system has installed plays no part
    ]
    if sources_list is not None:
        opts += [f"-o Dir::Etc::sourcelist={sources_list}", "-o Dir::Etc::sourceparts=-"]
    if os.geteuid() == 0:
        # As root, apt downloads as the _apt user, who cannot write into a cache under
        # /root: it would fall back to root with a warning; say so up front instead.
        opts.append("-o APT::Sandbox::User=root")
    return [word for opt in opts for word in opt.split(" ", 1)]


def _apt(opts: list[str], command: list[str], work: Path, cwd: Path, timeout_s: float) -> None:
    """Run ``apt-get -q OPTS COMMAND``, its output appended to ``work/apt.log``."""
    args = [*opts, *command]
    try:
        done = subprocess.run(
            ["apt-get", "-q", *args],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=False,
        )
    except FileNotFoundError as exc:
        raise WayFailed("apt-get not found") from exc
    except subprocess.TimeoutExpired as exc:
        raise WayFailed(f"apt-get {command[0]} timed out after {timeout_s:.0f} s") from exc
    with (work / "apt.log").open("a") as out:
        out.write(done.stdout + done.stderr)
    if done.returncode != 0:
        errors = [ln for ln in done.stderr.splitlines() if ln.startswith(("E:", "Err"))]
        tail = errors[-1] if errors else (done.stderr.strip().splitlines() or ["?"])[-1]
        raise WayFailed(f"apt-get {command[0]} failed: {tail[:200]}")


class PrivateApt:
    """apt-get with its own sources list (``suite`` of the system's Debian mirror) or the
    system's own sources (``suite=None``), and its own lists and cache, all in ``work``."""

    def __init__(
        self,
        work: Path,
        suite: str | None = None,
        mirror: Mirror | None = None,
        timeout_s: float = 300.0,
    ) -> None:
        self.work = work
        self.timeout_s = timeout_s
        (work / "lists" / "partial").mkdir(parents=True, exist_ok=True)
        (work / "cache" / "archives" / "partial").mkdir(parents=True, exist_ok=True)
        sources_list = None
        if suite is not None:
            mirror = mirror or debian_mirror(system_sources())
            sources_list = work / "sources.list"
            line = private_sources_line(mirror, suite, _signed_by_option(mirror, work))
            sources_list.write_text(line)
        self.opts = apt_options(work, sources_list)
        self.updated = False

    def update(self) -> None:
        if not self.updated:
            _apt(self.opts, ["update", "--error-on=any"], self.work, self.work, self.timeout_s)
            self.updated = True

    def download(self, packages: Sequence[str], dest: Path) -> list[Path]:
        """``apt-get download`` ``packages`` into ``dest``; returns the .deb files."""
        self.update()
        dest.mkdir(parents=True, exist_ok=True)
        before = set(dest.glob("*.deb"))
        _apt(self.opts, ["download", *packages], self.work, dest, self.timeout_s)
        debs = sorted(set(dest.glob("*.deb")) - before)
        if len(debs) < len(packages):
            raise WayFailed(f"apt-get download gave {len(debs)} of {len(packages)} packages")
        return debs

    def depends(self, package: str) -> list[str]:
        """The Depends of the candidate version of ``package``."""
        self.update()
        done = subprocess.run(
            ["apt-cache", *self.opts, "show", "--no-all-versions", package],
            capture_output=True,
            text=True,
            check=False,
        )
        for line in done.stdout.splitlines():
            if line.startswith("Depends:"):
                return [d.split()[0] for d in line[len("Depends:") :].split(",") if d.strip()]
        raise WayFailed(f"apt-cache show {package}: no Depends ({done.stderr.strip()[:120]})")


def unpack(deb: Path, root: Path) -> None:
    """``dpkg-deb -x``: the files of ``deb`` under ``root``, nothing installed."""
    root.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        ["dpkg-deb", "-x", str(deb), str(root)], capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise WayFailed(f"dpkg-deb -x {deb.name} failed: {done.stderr.strip()[:200]}")
