"""Vehicle configuration: pydantic models, built-in profiles and the TOML loader."""

from appliance.config.loader import (
    BUILTIN_PROFILES,
    ConfigError,
    ConfigProblem,
    load_config,
    parse_config,
)
from appliance.config.models import VehicleConfig

__all__ = [
    "BUILTIN_PROFILES",
    "ConfigError",
    "ConfigProblem",
    "VehicleConfig",
    "load_config",
    "parse_config",
]
