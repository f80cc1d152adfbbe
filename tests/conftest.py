"""Shared set-up: a temp dir per test is pytest's ``tmp_path``; helpers live in their own modules."""

import os
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

# One BLAS thread in the test processes, as ``nanodrift`` itself runs (daemon/blas_threads.py): OpenBLAS's
# threads made a small solve 100x slower on a loaded two-core machine. Imported before anything imports numpy
# (hypothesis does not).
from nanodrift import blas_threads  # noqa: F401

# tests import their helpers as the package ``helpers`` (tests/helpers/)
sys.path.insert(0, str(Path(__file__).parent))
from helpers.budget import LONG_TESTS, examples

# The suite starts a few hundred Python subprocesses (daemons, CLI commands). On a machine whose environment
# sets PYTHONDONTWRITEBYTECODE (some images do), each of them would compile nanodrift's modules anew; let the
# first one cache them (in __pycache__, which git ignores). Nothing tested depends on it.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False

# Hypothesis judges a test by its examples, not by how long a loaded machine took to run one: no deadline,
# and no "too slow" health check (time belongs in benchmarks/). A test's own @settings still add to this.
# "ci" (the default) draws a third of the examples hypothesis would (helpers.budget.examples, as the tests that
# name their count do); "release" (NANODRIFT_LONG_TESTS=1) all of them.
settings.register_profile("release", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("ci", settings.get_profile("release"), max_examples=examples(settings.default.max_examples))
settings.load_profile("release" if LONG_TESTS else "ci")

#: The files that take longest (a wheel build, a demo run, README blocks, chaos machines), run first: pytest-xdist
#: (``--dist loadfile``) hands out files in collection order, and one of these started last keeps the suite
#: waiting on one worker while the others are idle. Only the order changes; a file's tests stay together, in order.
LONG_FILES = (
    "tests/test_install_beside_python_daemon.py",
    "tests/commands/test_readme_verbatim.py",
    "tests/commands/test_demo.py",
    "tests/commands/test_demo_runs.py",
    "tests/service/test_chaos.py",
    "tests/service/test_chaos_serial.py",
    "tests/procedure/test_cell_procedure.py",
    "tests/service/test_hardware_edge.py",
    "tests/calibration/test_uncertainty_truth.py",
    "tests/service/test_secure_network.py",
    "tests/calibration/test_discovery.py",
    "tests/calibration/test_discovery_beyond_effects.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        path = item.nodeid.split("::")[0]
        return LONG_FILES.index(path) if path in LONG_FILES else len(LONG_FILES)

    items.sort(key=rank)  # stable: every other file keeps its place


@pytest.fixture(autouse=True)
def _structlog_as_a_fresh_process_has_it() -> object:
    """Each test starts with structlog unconfigured, as each command's process does: a test that configured
    it in-process (the daemon's JSON lines on stdout) would otherwise send a later command's driver logs into
    its ``--json`` output (``nanodrift.cli`` configures stderr only when nothing is configured)."""
    import structlog

    structlog.reset_defaults()
    yield
    structlog.reset_defaults()
