"""nanodrift installs one top-level import name, ``nanodrift``, and lives beside python-daemon.

Issue 25: the distribution used to install the top-level packages ``daemon`` and ``drivers``;
``pip install python-daemon`` overwrote ``daemon/__init__.py`` and uninstalling it deleted the file. Here a
stand-in distribution that installs a top-level ``daemon`` package (as python-daemon does) is installed
beside nanodrift in a fresh virtual environment, in both orders and with nanodrift editable; each time
``import daemon`` is the stand-in's, ``import nanodrift`` ours, the ``nanodrift`` command runs, and
uninstalling the stand-in leaves every file nanodrift installed.

The fresh environments get nanodrift's dependencies (and setuptools, for the editable build, and pip, which
runs in them) by a ``.pth`` line naming the test environment's site-packages: nothing is downloaded, and the
environment's own site-packages, where the two distributions go, comes first on ``sys.path``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

STANDIN_PYPROJECT = """\
[build-system]
requires = ["setuptools>=68"]
build-backend = "setuptools.build_meta"

[project]
name = "daemon-standin"
version = "1.0"

[tool.setuptools]
packages = ["daemon"]
"""

PROBE = """\
import json, daemon, nanodrift, nanodrift.cli
from nanodrift.drivers.registry import available
print(json.dumps({"daemon": getattr(daemon, "STANDIN", False), "daemon_file": daemon.__file__,
                  "nanodrift_file": nanodrift.__file__, "plugins": sorted(available())}))
"""


def pip(*args: str, python: Path = Path(sys.executable)) -> None:
    result = subprocess.run([str(python), "-m", "pip", "--disable-pip-version-check", "-q", *args],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.fixture(scope="module")
def wheels(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The two distributions as wheels: nanodrift from this tree, the stand-in made here."""
    out = tmp_path_factory.mktemp("wheels")
    standin = tmp_path_factory.mktemp("standin")
    (standin / "pyproject.toml").write_text(STANDIN_PYPROJECT)
    (standin / "daemon").mkdir()
    (standin / "daemon" / "__init__.py").write_text("STANDIN = True\n")
    pip("wheel", "--no-deps", "--no-build-isolation", "-w", str(out), str(REPO), str(standin))  # one pip run
    return {"nanodrift": next(out.glob("nanodrift-*.whl")), "standin": next(out.glob("daemon_standin-*.whl"))}


class Env:
    """A fresh virtual environment (no pip of its own: the test environment's pip, run by its python, installs into
    it)."""

    def __init__(self, root: Path) -> None:
        venv.create(root, with_pip=False)
        self.python = root / "bin" / "python"
        purelib = Path(self.run("import sysconfig; print(sysconfig.get_paths()['purelib'])").strip())
        (purelib / "zz_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
        self.root = root

    def run(self, code: str) -> str:
        result = subprocess.run([str(self.python), "-c", code], capture_output=True, text=True, timeout=60,
                                cwd=self.python.parent)  # not the repository: its daemon/ folder is not on the path
        assert result.returncode == 0, result.stderr
        return result.stdout

    # pip runs in the environment itself (the test environment's pip, through the .pth line): what
    # `pip --python` does too, after a first start of pip in the test environment that would cost each call ~0.2 s
    def install(self, *args: str) -> None:
        # --no-compile: no bytecode of every module up front (a third of an install's CPU); what runs compiles its own
        pip("install", "--no-deps", "--no-index", "--no-compile", *args, python=self.python)

    def uninstall(self, name: str) -> None:
        pip("uninstall", "-y", name, python=self.python)

    def probe(self) -> dict[str, object]:
        return json.loads(self.run(PROBE))

    def version(self) -> str:
        result = subprocess.run([str(self.root / "bin" / "nanodrift"), "--version"], capture_output=True,
                                text=True, timeout=60, cwd=self.root)
        assert result.returncode == 0, result.stderr
        return result.stdout

    def installed_files(self, distribution: str) -> list[Path]:
        """Every file pip recorded for ``distribution`` (its RECORD), as paths."""
        lines = self.run(f"import importlib.metadata as m; print('\\n'.join(str(f.locate()) for f in "
                         f"m.distribution({distribution!r}).files))")
        return [Path(line) for line in lines.splitlines() if line]


def check_both_work(env: Env, root: Path) -> dict[str, object]:
    """Both import as their own and the ``nanodrift`` command runs; what the probe found."""
    found = env.probe()
    assert found["daemon"] is True, found  # the stand-in's daemon, not a folder of nanodrift's
    assert Path(str(found["daemon_file"])).is_relative_to(root), found
    assert found["plugins"] == ["attocube_ids", "dcon", "modbus", "pi_gcs", "serial_line", "simulated"], found
    assert "nanodrift" in env.version()
    return found


@pytest.mark.parametrize("order", ["nanodrift first", "python-daemon first"])
def test_a_wheel_install_beside_a_top_level_daemon_package_in_either_order(
        tmp_path: Path, wheels: dict[str, Path], order: str) -> None:
    env = Env(tmp_path / "env")
    first, second = ("nanodrift", "standin") if order == "nanodrift first" else ("standin", "nanodrift")
    env.install(str(wheels[first]))
    env.install(str(wheels[second]))
    found = check_both_work(env, tmp_path / "env")
    assert Path(str(found["nanodrift_file"])).is_relative_to(tmp_path / "env")
    recorded = env.run("import importlib.metadata as m; print('\\n'.join(str(f) for f in m.files('nanodrift')))")
    top_level = {Path(line).parts[0] for line in recorded.splitlines() if not line.startswith("..")}
    assert top_level == {"nanodrift", "nanodrift-0.1.0.dist-info"}, top_level  # no daemon, no drivers
    ours = env.installed_files("nanodrift")
    env.uninstall("daemon-standin")
    missing = [p for p in ours if not p.exists()]
    assert not missing, missing
    assert "nanodrift" in env.version()
    assert "No module named 'daemon'" in subprocess.run([str(env.python), "-c", "import daemon"],
                                                        capture_output=True, text=True, cwd=tmp_path).stderr


def test_an_editable_install_beside_a_top_level_daemon_package(tmp_path: Path, wheels: dict[str, Path]) -> None:
    env = Env(tmp_path / "env")
    env.install(str(wheels["standin"]))
    env.install("--no-build-isolation", "-e", str(REPO))
    found = check_both_work(env, tmp_path / "env")
    assert Path(str(found["nanodrift_file"])) == REPO / "daemon" / "__init__.py"  # the tree, as edited
    env.uninstall("daemon-standin")
    assert (REPO / "daemon" / "__init__.py").is_file()
    assert "nanodrift" in env.version()
