"""Loading a vehicle profile from TOML and explaining what is wrong with it.

A person editing a config on the vehicle needs one line per problem that names the field,
what was given and what is allowed. Pydantic's own messages say "less than or equal to 20"
but not which field family or unit; here we add the path in TOML notation and the
allowed range read from the model itself, so the message can never disagree with the check.
"""

from __future__ import annotations

import difflib
import json
import tomllib
import types
import typing
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import annotated_types
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo

from appliance.config.models import VehicleConfig

BUILTIN_PROFILES = (
    "sim",
    "flatbed",
    "flatbed-sim",
    "husky",
    "husky-sim",
    "forklift",
    "forklift-sim",
)


@dataclass(frozen=True)
class ConfigProblem:
    """One thing wrong with a config file, ready to print."""

    field: str
    message: str

    def __str__(self) -> str:
        return f"{self.field}: {self.message}" if self.field else self.message


class ConfigError(Exception):
    """A config that cannot be used; carries every problem found, not just the first."""

    def __init__(self, source: str, problems: list[ConfigProblem]) -> None:
        self.source = source
        self.problems = problems
        super().__init__(self.render())

    def render(self) -> str:
        lines = [f"{self.source}: {len(self.problems)} problem(s)"]
        lines += [f"  - {problem}" for problem in self.problems]
        return "\n".join(lines)


def load_config(name_or_path: str | Path | None = None) -> VehicleConfig:
    """Load a built-in profile by name (``sim``, ``flatbed``, ``husky``) or a TOML file.

    ``None`` means the built-in ``sim`` profile, so the daemon runs with no file at all.
    """
    if name_or_path is None:
        name_or_path = "sim"
    if isinstance(name_or_path, str) and name_or_path in BUILTIN_PROFILES:
        text = (
            resources.files("appliance.config")
            .joinpath("profiles", f"{name_or_path}.toml")
            .read_text(encoding="utf-8")
        )
        return parse_config(text, source=f"built-in profile {name_or_path!r}")
    path = Path(name_or_path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(
            str(path),
            [
                ConfigProblem(
                    "",
                    "no such file (built-in profiles are: " + ", ".join(BUILTIN_PROFILES) + ")",
                )
            ],
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(str(path), [ConfigProblem("", f"cannot read the file: {exc}")]) from None
    return parse_config(text, source=str(path))


def parse_config(text: str, source: str = "<config>") -> VehicleConfig:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(source, [ConfigProblem("", f"not valid TOML: {exc}")]) from None
    try:
        return VehicleConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(source, explain(exc)) from None


def explain(exc: ValidationError, root: type[BaseModel] = VehicleConfig) -> list[ConfigProblem]:
    """One problem per validation error of ``root`` (a vehicle file, a site file, ...)."""
    problems = []
    for error in exc.errors(include_url=False):
        loc = tuple(error["loc"])
        field = _toml_path(loc)
        if error["type"] == "extra_forbidden":
            problems.append(ConfigProblem(field, _unknown_field_message(loc, root)))
            continue
        message = str(error["msg"]).removeprefix("Value error, ")
        if error["type"] != "missing" and not isinstance(error.get("input"), dict | list):
            message += f" (got {error.get('input')!r})"
        _, info = _walk(loc, root)
        allowed = "" if error["type"] == "missing" or info is None else _allowed(info)
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


def _walk(
    loc: tuple[Any, ...], root: type[BaseModel]
) -> tuple[type[BaseModel] | None, FieldInfo | None]:
    """Follow an error location through the models: (the parent model, the field info)."""
    model: type[BaseModel] | None = root
    info: FieldInfo | None = None
    for part in loc:
        if isinstance(part, int):
            continue
        if model is None or part not in model.model_fields:
            return None, None
        info = model.model_fields[part]
        model = _model_of(info.annotation)
    return model, info


def _unknown_field_message(loc: tuple[Any, ...], root: type[BaseModel]) -> str:
    parent, _ = _walk(loc[:-1], root)
    known = sorted(parent.model_fields) if parent is not None else []
    suggestion = difflib.get_close_matches(str(loc[-1]), known, n=1)
    if suggestion:
        return f"unknown field; did you mean {suggestion[0]!r}?"
    return "unknown field" + ("; known fields here: " + ", ".join(known) if known else "")


def _allowed(info: FieldInfo) -> str:
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
    if lower or upper:
        return lower or upper
    choices = getattr(info.annotation, "__members__", None)
    if choices:
        return ", ".join(repr(member.value) for member in choices.values())
    return ""


def _toml_value(value: object) -> str:
    """A value as TOML writes it: JSON's spelling for scalars and arrays, but a table in
    an array (``lookahead_tuning.conditions``) inline as ``{key = value}``."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return json.dumps(value)


def to_toml(data: dict[str, object], prefix: str = "") -> str:
    """Render the effective config in TOML so it can be copied into a vehicle file."""
    # TOML has no null: an optional field left unset is simply not written.
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict) and v is not None}
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    lines = []
    if prefix and scalars:
        lines.append(f"[{prefix}]")
    for key, value in scalars.items():
        lines.append(f"{key} = {_toml_value(value)}")
    out = "\n".join(lines)
    for key, value in tables.items():
        assert isinstance(value, dict)
        sub = to_toml(value, f"{prefix}.{key}" if prefix else key)
        out = f"{out}\n\n{sub}" if out else sub
    return out
