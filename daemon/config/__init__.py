"""The operator's TOML config, validated by pydantic (the contract in the README): the one public surface.

Callers import from here only; the modules behind it each do one job:

- :mod:`nanodrift.settings` (outside this package, so that importing a table never starts plugin
  discovery): the daemon's own tables as plain pydantic models, and :class:`Config`;
- ``_dispatch``: which plugin validates which table, sensor, hub and actuator; every problem collected;
- ``_checks``: checks across the daemon's own tables (points in the workspace, believable ranges);
- ``_lines``: where a problem is: ``<file>:<line>: <path>: <message>``, e.g.
  ``lab.toml:42: sensors[5] (T6).scale: Input should be a valid number``;
- ``_load``: reading the file (or the built-in default).

Unknown keys are errors everywhere: a typo must never pass silently, and numbers are strict:
``scale = "0.1"`` (a string) is an error, not 0.1.
"""

from nanodrift.config._checks import DEFAULT_TEMPERATURE_RANGE_C, missing_model_channels, valid_range
from nanodrift.config._dispatch import actuator_line, parse_config
from nanodrift.config._lines import ConfigError, locate
from nanodrift.config._load import TOO_DEEP, default_config, load_config
from nanodrift.settings import (
    BUILTIN_SOURCE,
    DEFAULT_MODEL_PATH,
    MAX_RECORD_KEEP_DAYS,
    MIN_SLEW_UM_PER_S,
    SAFE_RAMP_BUDGET_S,
    STOP_TIMEOUT_S,
    ZENOH_KIND,
    ActuatorConfig,
    Config,
    HealthSettings,
    ZenohSettings,
)

__all__ = [
    "BUILTIN_SOURCE",
    "DEFAULT_MODEL_PATH",
    "DEFAULT_TEMPERATURE_RANGE_C",
    "MAX_RECORD_KEEP_DAYS",
    "MIN_SLEW_UM_PER_S",
    "SAFE_RAMP_BUDGET_S",
    "STOP_TIMEOUT_S",
    "TOO_DEEP",
    "ZENOH_KIND",
    "ActuatorConfig",
    "Config",
    "ConfigError",
    "HealthSettings",
    "ZenohSettings",
    "actuator_line",
    "default_config",
    "load_config",
    "locate",
    "missing_model_channels",
    "parse_config",
    "valid_range",
]
