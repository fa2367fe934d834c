"""Site files: a TOML description of a simulated site, validated before anything runs.

A site is described by what is in it, not by raw geometry: ``[launcher]`` with a pose
and a few dimensions, ``[[pallet_areas]]``, ``[[posts]]``, ``[[walkers]]``, free
``[[segments]]`` and an optional ``[yard]`` boundary. The tables are validated into the
builders' own spec models, so a file and a Python test build identical shapes. Unknown
keys are errors (a misspelled ``cylinder_radius_m`` must not silently fall back to the
default), and every problem is reported with its field path in TOML notation, e.g.
``walkers[0].speed_mps``, through the same ``ConfigError`` the vehicle config uses.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path

from pydantic import ValidationError

from appliance.config import ConfigError, ConfigProblem
from appliance.config.loader import explain
from appliance.sim.builders import (
    LauncherSpec,
    PalletAreaSpec,
    PostSpec,
    SegmentSpec,
    WalkerSpec,
    YardSpec,
    _Spec,
    clutter_site,
    launcher_site,
    pallet_area_site,
    yard_site,
)
from appliance.sim.site import Site

SITES_PACKAGE = "appliance.sim"
SITES_FOLDER = "sites"


class SiteError(ConfigError):
    """A site file that cannot be used; lists every problem with its field path."""


class SiteFile(_Spec):
    """The whole of one site file; every table is optional."""

    name: str = ""
    yard: YardSpec | None = None
    launcher: LauncherSpec | None = None
    pallet_areas: tuple[PalletAreaSpec, ...] = ()
    posts: tuple[PostSpec, ...] = ()
    walkers: tuple[WalkerSpec, ...] = ()
    segments: tuple[SegmentSpec, ...] = ()

    def build(self) -> Site:
        site = Site(name=self.name)
        if self.yard is not None:
            site = site.merged(yard_site(self.yard))
        if self.launcher is not None:
            site = site.merged(launcher_site(self.launcher))
        for area in self.pallet_areas:
            site = site.merged(pallet_area_site(area))
        return site.merged(clutter_site(self.posts, self.walkers, self.segments))


def builtin_site_names() -> tuple[str, ...]:
    folder = resources.files(SITES_PACKAGE).joinpath(SITES_FOLDER)
    return tuple(
        sorted(
            entry.name.removesuffix(".toml")
            for entry in folder.iterdir()
            if entry.name.endswith(".toml")
        )
    )


def load_site(name_or_path: str | Path) -> Site:
    """A built-in site by name (``launcher``, ``pallets``) or a site TOML file by path."""
    if isinstance(name_or_path, str) and name_or_path in builtin_site_names():
        text = (
            resources.files(SITES_PACKAGE)
            .joinpath(SITES_FOLDER, f"{name_or_path}.toml")
            .read_text(encoding="utf-8")
        )
        return parse_site(text, source=f"built-in site {name_or_path!r}", default_name=name_or_path)
    path = Path(name_or_path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        known = ", ".join(builtin_site_names())
        raise SiteError(
            str(path), [ConfigProblem("", f"no such file (built-in sites are: {known})")]
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SiteError(str(path), [ConfigProblem("", f"cannot read the file: {exc}")]) from None
    return parse_site(text, source=str(path), default_name=path.stem)


def parse_site(text: str, source: str = "<site>", default_name: str = "") -> Site:
    """Validate a site file's text and build the site; raises ``SiteError``."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SiteError(source, [ConfigProblem("", f"not valid TOML: {exc}")]) from None
    data.setdefault("name", default_name)
    try:
        site_file = SiteFile.model_validate(data)
    except ValidationError as exc:
        raise SiteError(source, explain(exc, SiteFile)) from None
    return site_file.build()
