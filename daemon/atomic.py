"""Write files so a reader sees the old content or the new one, never half of either.

Temp file in the same directory, fsync, then ``os.replace``: a crash or a full disk leaves the
previous file in place (the rule: nothing is written non-atomically). A path that is a symbolic link is
written *through*: the file it names is replaced and the link stays, as ``open(path, "w")`` would do.
Labs keep ``model.json -> models/m-2026-11.json`` and switch models by moving the link; replacing the
link by a regular file would silently cut that, and leave the named file stale. Also the checksum that ties a
model to the data file it was made from. Stdlib only: part of the pure core, usable everywhere.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike[str], mode: str = "w", encoding: str | None = "utf-8") -> Iterator[IO[Any]]:
    """Yield a file object; on clean exit it replaces ``path`` (the file a symbolic link names, the link
    kept; an existing file's mode, and its owner and group where this user may set them), on error
    ``path`` is untouched."""
    target = Path(os.path.realpath(path))
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        _keep_owner(tmp, target)
        os.chmod(tmp, _mode_for(target))  # after chown, which may clear set-id bits
        with os.fdopen(fd, mode, encoding=None if "b" in mode else encoding) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # make the rename itself durable
        dir_fd = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def _keep_owner(tmp: str, target: Path) -> None:
    """Give the new file the replaced one's owner and group (``root:nogroup`` config edited by root stays
    ``root:nogroup``). Only root may give a file away, and a user only to a group of theirs: otherwise
    the new file is the writer's, as any new file."""
    try:
        stat = target.stat()
    except FileNotFoundError:
        return
    with contextlib.suppress(PermissionError):
        os.chown(tmp, stat.st_uid, stat.st_gid)


def _mode_for(target: Path) -> int:
    """Keep an existing file's permissions; a new file gets what ``open()`` would give (0666 & ~umask).

    ``mkstemp`` creates 0600, which would make a model written by an operator unreadable by the
    daemon's own user.
    """
    try:
        return target.stat().st_mode & 0o7777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    with atomic_writer(path, "w") as handle:
        handle.write(text)


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Hex SHA-256 of a file's bytes, read in blocks (a recorded run can be large)."""
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()
