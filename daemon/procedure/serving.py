"""``calibrate --serve``: point a config's ``[model] path`` at the new model, keeping the rest of its text.

Only the ``path`` line of ``[model]`` changes (added when missing, the previous one kept as a comment);
every other line, comment and blank of the operator's file stays as it was, and so do its line endings
(CRLF stays CRLF), its mode, and its owner and group where this user may set them. The new text is parsed
and validated as the daemon would read it before it replaces the file, atomically: a config that would
not serve the new model is never written.
"""

from __future__ import annotations

import os
import re
import tomllib
from datetime import UTC, datetime
from pathlib import Path

from nanodrift.atomic import atomic_writer
from nanodrift.config import ConfigError, parse_config

#: a table header line: ``[model]``, ``[[sensors]]`` (a comment may follow)
_HEADER = re.compile(r"^\s*\[\[?\s*(?P<name>[A-Za-z0-9_.\-\"' ]+?)\s*\]\]?\s*(?:#.*)?$")
_PATH_KEY = re.compile(r"^(?P<indent>\s*)path\s*=")


#: who wrote the line, in the comments it leaves
NOTE = "nanodrift calibrate --serve"


def toml_string(value: str) -> str:
    """``value`` as a TOML basic string: quotes, backslashes and control characters (DEL too) escaped."""
    escaped = value.replace("\\", "\\\\").replace('"', '\\"')
    return '"' + "".join(f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else c for c in escaped) + '"'


class ServeError(Exception):
    """The config cannot be made to serve the model; the message says why and what to do by hand."""


def check_writable(config_path: Path) -> None:
    """Refuse before hours of calibration when the config cannot be replaced (the file or its folder)."""
    folder = config_path.resolve().parent
    for what, path in (("the file", config_path), ("its folder", folder)):
        if not os.access(path, os.W_OK):
            raise ServeError(f"--serve: cannot write {config_path} ({what} is not writable by this user): run as "
                             "the config's owner (root for /etc/nanodrift), or leave out --serve and set "
                             "[model] path by hand")


def _is_model_header(line: str) -> bool:
    found = _HEADER.match(line)
    return found is not None and not line.lstrip().startswith("[[") and found["name"].strip("\"' ") == "model"


def with_model_path(text: str, model_path: Path, note: str) -> str:
    """``text`` with ``[model] path = "<model_path>"``: the existing line replaced (kept as a comment above
    it, ``note`` saying by whom), or a new line at the end of the table's first paragraph, or a new table."""
    newline = "\r\n" if "\r\n" in text else "\n"
    lines = [line for line in re.split(r"(?<=\n)", text) if line]  # TOML's lines: not str.splitlines' (\x85, ...)
    value = f"path = {toml_string(str(model_path))}"
    headers = [i for i, line in enumerate(lines) if _HEADER.match(line)]
    start = next((i for i in headers if _is_model_header(lines[i])), None)
    if start is None:
        ending = "" if not text or text.endswith(("\n", "\r")) else newline
        return f"{text}{ending}{newline}[model]{newline}{value}   # {note}{newline}"
    end = next((i for i in headers if i > start), len(lines))
    for index in range(start + 1, end):
        found = _PATH_KEY.match(lines[index])
        if found:
            indent = found["indent"]
            previous = lines[index].rstrip("\r\n").strip()
            lines[index] = f"{indent}{value}{newline}"
            # one such comment, not a pile: an earlier one is replaced
            kept = index - 1 if lines[index - 1].lstrip().startswith(f"# before {NOTE}") else index
            lines[kept:index] = [f"{indent}# before {note}: {previous}{newline}"]
            return "".join(lines)
    paragraph_end = start + 1
    while paragraph_end < end and lines[paragraph_end].strip():
        paragraph_end += 1
    lines.insert(paragraph_end, f"{value}   # {note}{newline}")
    return "".join(lines)


def _served_path(text: str, config_path: Path) -> Path:
    """The model file a config's text serves, as the daemon resolves it; :class:`ServeError` if it is invalid."""
    try:
        config = parse_config(tomllib.loads(text), source=str(config_path), base_dir=config_path.resolve().parent)
    except (tomllib.TOMLDecodeError, ValueError, ConfigError) as error:
        raise ServeError(f"--serve: {config_path} would not be a valid config ({error})") from None
    return Path(config.model.path).resolve()


def serve_model(config_path: Path, model_path: Path) -> bool:
    """Make ``config_path`` serve ``model_path`` (an absolute path is written), atomically; False when it
    already did (the file is left as it is).

    The new text must parse, pass the daemon's config checks and name ``model_path`` as its model;
    otherwise :class:`ServeError` and the file is untouched.
    """
    config_path = config_path.resolve()  # a symlinked config: its file is edited, the link stays a link
    check_writable(config_path)
    model_path = model_path.resolve()
    with open(config_path, encoding="utf-8", newline="") as handle:  # newline="": CRLF is read as it is
        text = handle.read()
    by_hand = f"it is unchanged: set [model] path = {toml_string(str(model_path))} by hand"
    try:
        if _served_path(text, config_path) == model_path:
            return False
        stamp = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
        new_text = with_model_path(text, model_path, f"{NOTE}, {stamp}")
        served = _served_path(new_text, config_path)
    except ServeError as error:
        raise ServeError(f"{error}; {by_hand}") from None
    if served != model_path:
        raise ServeError(f"--serve: could not place the model's path in {config_path} (it would still serve "
                         f"{served}); {by_hand}")
    try:
        with atomic_writer(config_path, "wb") as handle:  # bytes: the line endings are the text's own
            handle.write(new_text.encode("utf-8"))
    except OSError as error:
        raise ServeError(f"--serve: cannot write {config_path}: {error}; {by_hand}") from None
    return True
