"""Reading the operator's TOML file (or the built-in default) into a validated :class:`Config`.

Every refusal is a :class:`ConfigError`, a hostile file included; the problems of a file that parses
get their line (:func:`~nanodrift.config._lines.locate`).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from nanodrift.config._dispatch import parse_config
from nanodrift.config._lines import ConfigError, locate
from nanodrift.settings import BUILTIN_SOURCE, Config


def load_config(path: str | Path | None) -> Config:
    """The config in ``path`` (TOML), or the built-in default (simulated cell) when ``path`` is None."""
    if path is None:
        return default_config()
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(str(file), ["file not found"]) from None
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(str(file), [f"cannot read: {error}"]) from None
    try:  # a hostile file ('x = ' + '[' * 100000) must be a message, never a traceback or a dead reload
        data = tomllib.loads(text)
    except RecursionError:
        raise ConfigError(str(file), [TOO_DEEP]) from None
    except MemoryError:
        raise ConfigError(str(file), ["not valid TOML: too large to parse"]) from None
    except ValueError as error:  # TOMLDecodeError and tomllib's other refusals (an out-of-range date, ...)
        raise ConfigError(str(file), [f"not valid TOML: {error}"]) from None
    try:
        return parse_config(data, source=str(file), base_dir=file.resolve().parent)
    except ConfigError as error:
        raise ConfigError(error.source, error.problems, [locate(text, p) for p in error.problems]) from None
    except RecursionError:
        raise ConfigError(str(file), [TOO_DEEP]) from None


#: the problem line of a config whose arrays or inline tables nest deeper than the parser can follow
TOO_DEEP = "not valid TOML: nested too deeply (a nanodrift config nests a few levels of [ and {, not hundreds)"


#: the built-in config of ``nanodrift run`` with no ``--config``: the simulated cell's table (data, not an import)
BUILTIN_CONFIG: dict[str, Any] = {"simulation": {"scenario": "room"}}


def default_config() -> Config:
    """No file: the simulated cell in a room inside the shipped model's training range, served with that model.

    Extrapolation is then a finding, not the first thing a new user sees; ``[simulation] scenario``
    (``test5``, ``daily``) shows it on purpose.
    """
    return parse_config(BUILTIN_CONFIG, source=BUILTIN_SOURCE)
