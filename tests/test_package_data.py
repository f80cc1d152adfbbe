"""Files the installed package reads or points readers at are shipped with it (pyproject package-data).

The project is installed editable here, so :mod:`importlib.resources` alone would find any file of
the source tree; the patterns in ``pyproject.toml`` are what a wheel ships, so both are checked.
"""

from __future__ import annotations

import fnmatch
import tomllib
from importlib.resources import files
from pathlib import Path

import pytest

from nanodrift.reports.discovery import METHOD_DOC

REPO = Path(__file__).resolve().parents[1]


SETUPTOOLS = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]


def shipped(relative: str) -> bool:
    """Whether a wheel built from pyproject.toml carries ``relative`` (a path under the repository)."""
    folder, _, inside = relative.partition("/")
    package = next(name for name, where in SETUPTOOLS["package-dir"].items() if where == folder)
    return any(fnmatch.fnmatch(inside, pattern) for pattern in SETUPTOOLS["package-data"].get(package, []))


def test_every_folder_of_the_package_is_installed_under_nanodrift_and_nothing_else_at_top_level() -> None:
    """A subpackage missing from pyproject's list would be absent from a wheel (an editable install hides it)."""
    folders = {}
    for package, folder in SETUPTOOLS["package-dir"].items():
        for init in (REPO / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(REPO / folder).parts
            folders[".".join([package, *parts])] = init.parent
    assert sorted(SETUPTOOLS["packages"]) == sorted(folders)
    assert {name.split(".")[0] for name in SETUPTOOLS["packages"]} == {"nanodrift"}
    assert files("nanodrift").joinpath("py.typed").is_file() and shipped("daemon/py.typed")


def test_the_discovery_method_the_report_points_to_is_an_installed_resource() -> None:
    assert METHOD_DOC == "daemon/calibration/discovery/METHOD.md"
    resource = files("nanodrift.calibration.discovery").joinpath("METHOD.md")
    assert resource.is_file()
    assert resource.read_text(encoding="utf-8").lstrip().startswith("#")  # the document, not an empty stub
    assert shipped(METHOD_DOC), "pyproject.toml's package-data does not ship it: installed readers find nothing"


@pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "daemon" / "data").iterdir() if p.is_file()))
def test_every_shipped_data_file_is_in_package_data(name: str) -> None:
    assert files("nanodrift").joinpath("data", name).is_file()
    assert shipped(f"daemon/data/{name}")


def test_the_check_itself_refuses_a_file_no_pattern_names() -> None:
    assert not shipped("daemon/calibration/discovery/NOTES.md")
    assert not shipped("daemon/data/unknown.bin")
