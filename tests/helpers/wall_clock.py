"""Step the wall clock of a daemon under test (its process only): see ``wall_shift/sitecustomize.py``."""

from __future__ import annotations

from pathlib import Path

from nanodrift.atomic import atomic_write_text

SITE_DIR = Path(__file__).resolve().parent / "wall_shift"


class WallShift:
    """A file holding the daemon's wall-clock offset in seconds; :meth:`step` changes it at once.

    ``Daemon(..., extra_pythonpath=[WallShift.SITE_DIR], env=shift.env())`` starts a daemon whose
    ``time.time()`` follows the file.
    """

    SITE_DIR = SITE_DIR

    def __init__(self, path: Path) -> None:
        self.path = path
        self.offset_s = 0.0
        atomic_write_text(path, "0\n")

    def env(self) -> dict[str, str]:
        return {"NANODRIFT_WALL_SHIFT_FILE": str(self.path)}

    def step(self, seconds: float) -> None:
        """Step the wall clock by ``seconds`` (negative: backwards), on top of earlier steps."""
        self.offset_s += seconds
        atomic_write_text(self.path, f"{self.offset_s!r}\n")  # a new inode: the daemon sees it at once
