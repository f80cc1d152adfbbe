"""Type-check the import package ``nanodrift`` as it is installed, from the design card's folders.

The folders ``daemon/`` and ``drivers/`` are installed as ``nanodrift`` and ``nanodrift.drivers``
(setuptools ``package-dir``). mypy finds packages by folder name and does not follow setuptools'
editable import hook, so this lays out ``build/typecheck/nanodrift`` as links to the real files (the
layout a wheel has) and checks ``-p nanodrift`` there, with the ``[tool.mypy]`` settings of
pyproject.toml. Extra arguments go to mypy. ``python scripts/typecheck.py``; exit status is mypy's.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TREE = REPO / "build" / "typecheck"


def link_tree() -> Path:
    """``build/typecheck/nanodrift``: every entry of daemon/ linked, and ``drivers`` linked to drivers/."""
    package = TREE / "nanodrift"
    if TREE.exists():
        shutil.rmtree(TREE)
    package.mkdir(parents=True)
    for entry in (REPO / "daemon").iterdir():
        if entry.name != "__pycache__":
            (package / entry.name).symlink_to(entry)
    (package / "drivers").symlink_to(REPO / "drivers")
    return TREE


def main() -> int:
    tree = link_tree()
    command = [sys.executable, "-m", "mypy", "--config-file", str(REPO / "pyproject.toml"), "-p", "nanodrift",
               *sys.argv[1:]]
    return subprocess.run(command, cwd=tree, check=False).returncode


if __name__ == "__main__":
    sys.exit(main())
