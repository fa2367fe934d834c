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

import difflib
import tomllib
import types
import typing
from importlib import resources
from pathlib import Path
from typing import Any

import annotated_types
from pydantic import BaseModel, ValidationError

from appliance.config import ConfigError, ConfigProblem
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
        raise SiteError(source, _explain(exc)) from None
    return site_file.build()


def _explain(exc: ValidationError) -> list[ConfigProblem]:
    problems = []
    for error in exc.errors(include_url=False):
        loc = tuple(error["loc"])
        field = _toml_path(loc)
        if error["type"] == "extra_forbidden":
            problems.append(ConfigProblem(field, _unknown_field_message(loc)))
            continue
        message = str(error["msg"]).removeprefix("Value error, ")
        if error["type"] != "missing" and not isinstance(error.get("input"), dict | list):
            message += f" (got {error.get('input')!r})"
        allowed = "" if error["type"] == "missing" else _allowed(loc)
        if allowed:
            message += f"; allowed: {allowed}"
        problems.append(ConfigProblem(field, message))
    return problems


def _toml_path(loc: tuple[Any, ...]) -> str:
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


def _model_of(annotation: Any) -> type[BaseModel] | None:
    """The model inside ``X``, ``X | None`` or ``tuple[X, ...]``, if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is not None:
        for arg in typing.get_args(annotation):
            model = _model_of(arg)
            if model is not None:
                return model
    return None


def _walk(loc: tuple[Any, ...]) -> tuple[type[BaseModel] | None, Any]:
    """Follow an error location through the models: (the parent model, the field info)."""
    model: type[BaseModel] | None = SiteFile
    info: Any = None
    for part in loc:
        if isinstance(part, int):
            continue
        if model is None or part not in model.model_fields:
            return None, None
        info = model.model_fields[part]
        model = _model_of(info.annotation)
    return model, info


def _unknown_field_message(loc: tuple[Any, ...]) -> str:
    parent, _ = _walk(loc[:-1])
    known = sorted(parent.model_fields) if parent is not None else []
    suggestion = difflib.get_close_matches(str(loc[-1]), known, n=1)
    if suggestion:
        return f"unknown field; did you mean {suggestion[0]!r}?"
    return "unknown field" + ("; known fields here: " + ", ".join(known) if known else "")


def _allowed(loc: tuple[Any, ...]) -> str:
    _, info = _walk(loc)
    if info is None:
        return ""
    lower = upper = ""
    for meta in info.metadata:
        if isinstance(meta, annotated_types.Ge):
            lower = f"{meta.ge} <= value"
        elif isinstance(meta, annotated_types.Gt):
            lower = f"{meta.gt} < value"
        elif isinstance(meta, annotated_types.Le):
            upper = f"value <= {meta.le}"
        elif isinstance(meta, annotated_types.Lt):
            upper = f"value < {meta.lt}"
    if lower and upper:
        return lower + upper.removeprefix("value")
    return lower or upper
