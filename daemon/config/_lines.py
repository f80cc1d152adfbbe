"""Where a config problem is: its field path (``sensors[5] (T6).scale``) and its line in the TOML text.

Pydantic errors become ``path: message`` lines (:func:`problems_of`); ``tomllib`` keeps no positions,
so :func:`locate` finds a path's line in the text (the n-th ``[[sensors]]`` header, then the key inside
it), and :class:`ConfigError` shows each problem as ``<file>:<line>: <path>: <message>``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

from pydantic import ValidationError

from nanodrift.errors import UserError


class ConfigError(UserError):
    """An invalid config; ``problems`` holds one ``path: message`` line per problem, ``lines`` the
    line of the file each one is at (None when unknown); the message shows ``file:line: problem``."""

    def __init__(self, source: str, problems: Sequence[str], lines: Sequence[int | None] | None = None) -> None:
        self.source = source
        self.problems = list(problems)
        self.lines = list(lines) if lines is not None else [None] * len(self.problems)
        text = "\n".join(f"{source}:{line}: {p}" if line else f"{source}: {p}"
                         for p, line in zip(self.problems, self.lines, strict=True))
        super().__init__(text)


#: pydantic puts the union member that failed in ``loc`` (``effects.list[str]``, ``port.int``): it names no key
_UNION_MEMBER = re.compile(r"^(?:[a-z][a-z-]*\[.*\]|int|float|str|bool|none)$")


def field_path(prefix: str, loc: Sequence[Any], unknown_key: bool = False) -> str:
    """``sensors[5] (T6).scale``: ``prefix`` and pydantic's ``loc`` of an error, without union members."""
    path = prefix
    for position, part in enumerate(loc):
        last_is_the_key = unknown_key and position == len(loc) - 1  # a key the user wrote, whatever it is
        if isinstance(part, str) and _UNION_MEMBER.match(part) and not last_is_the_key:
            continue
        if isinstance(part, int):
            path += f"[{part}]"
        else:
            path += f".{part}" if path else str(part)
    return path or "(top level)"


def problems_of(prefix: str, error: ValidationError) -> list[str]:
    """One ``path: message`` line per error of a validation of the table at ``prefix``."""
    out = []
    for item in error.errors(include_url=False):
        message = item["msg"]
        if item["type"] == "extra_forbidden":
            message = "unknown key (typo?)"
        out.append(f"{field_path(prefix, item['loc'], item['type'] == 'extra_forbidden')}: {message}")
    return out


def sensor_where(index: int, sensor: Any) -> str:
    """``sensors[5] (T6)``: the index in the file's order (0-based) and the sensor's name when it has one."""
    name = sensor.get("name") if isinstance(sensor, Mapping) else getattr(sensor, "name", None)
    return f"sensors[{index}] ({name})" if isinstance(name, str) and name else f"sensors[{index}]"


_PROBLEM_PATH = re.compile(r"^(?P<table>[A-Za-z_][\w-]*)(?:\[(?P<index>\d+)\])?(?: \([^)]*\))?(?:\.(?P<key>[\w-]+))?")
_ARRAY_HEADER = re.compile(r"^\s*\[\[\s*(?P<name>[\w.-]+)\s*\]\]")
_TABLE_HEADER = re.compile(r"^\s*\[\s*(?P<name>[\w.-]+)\s*\]")


def locate(text: str, problem: str) -> int | None:
    """The 1-based line of ``text`` a problem (``sensors[5] (T6).scale: ...``) is at, or None.

    The key's own line when it is written in its table, else the line where the table starts (the
    n-th ``[[sensors]]`` header for ``sensors[n]``); a top-level key's line before any table.
    """
    match = _PROBLEM_PATH.match(problem)
    if match is None:
        return None
    table, index, key = match["table"], match["index"], match["key"]
    lines = text.splitlines()
    headers: list[tuple[int, str, bool]] = []  # (0-based line, name, is an array of tables)
    for number, line in enumerate(lines):
        header = _ARRAY_HEADER.match(line) or _TABLE_HEADER.match(line)
        if header:
            headers.append((number, header["name"], header.re is _ARRAY_HEADER))
    if index is not None:
        starts = [n for n, name, array in headers if name == table and array]
        start = starts[int(index)] if int(index) < len(starts) else None
    else:
        start = next((n for n, name, array in headers if name == table and not array), None)
    if start is None:  # a top-level key (``cell = ...``, ``sensors = 3``), written before any table
        end = headers[0][0] if headers else len(lines)
        return _key_line(lines, table, 0, end)
    if key is None:
        return start + 1
    end = next((n for n, _, _ in headers if n > start), len(lines))
    if index is not None and key in _SUBTABLES.get(table, ()):  # axes[1] (y).actuator.kind: in [axes.actuator]
        sub = next((n for n, name, array in headers if n > start and ((array and name == table)
                    or name == f"{table}.{key}")), None)
        if sub is not None and headers[[h[0] for h in headers].index(sub)][1] == f"{table}.{key}":
            rest = problem[match.end():]
            sub_key = re.match(r"\.(?P<k>[\w-]+)", rest)
            sub_end = next((n for n, _, _ in headers if n > sub), len(lines))
            found = _key_line(lines, sub_key["k"], sub + 1, sub_end) if sub_key else None
            return found or sub + 1
    return _key_line(lines, key, start + 1, end) or start + 1


#: an array of tables' sub-table (``[axes.actuator]`` inside each ``[[axes]]``)
_SUBTABLES = {"axes": ("actuator",)}


def _key_line(lines: Sequence[str], key: str, start: int, end: int) -> int | None:
    pattern = re.compile(rf"^\s*{re.escape(key)}\s*=")
    return next((n + 1 for n in range(start, end) if pattern.match(lines[n])), None)
