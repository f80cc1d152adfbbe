"""The plugin contract kit (``nanodrift.drivers.testing.contract``) used from outside nanodrift, as a lab uses it.

A stand-alone plugin package is written to ``tmp_path`` (a module and the ``*.dist-info`` that ``pip
install`` would leave, declaring it in ``nanodrift.drivers``) beside a lab's test file that imports only
the kit and defines rigs: the README's example, verbatim, plus the same rig on a lying box. ``python -m
pytest`` runs that file in a subprocess, outside nanodrift's test suite and its configuration. The
honest box passes every check (the multi-output ones skipped with the rig's reason); the box whose
``sent_voltage`` lies fails, and pytest names the checks it failed.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

from helpers.daemon_harness import REPO

from nanodrift.drivers import registry

#: the lab's plugin, the box of the README's example: one output of 0..10 V in 1 mV steps (a DAC: a voltage
#: near a limit is written as the count on the inside), emulated by a file of JSON lines (the last line is held)
PLUGIN_SOURCE = '''
"""A lab's output box as a nanodrift driver plugin: no sensors, one output."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

from nanodrift.drivers.base import (Actuator, ActuatorOptions, DeviceError, DriverContext, DriverPlugin,
                                    SensorConfig, SensorGroup)

STEP_V = 0.001
FULL_SCALE_V = 10.0


class BoxOptions(ActuatorOptions):
    kind: Literal["mybox", "liarbox"] = "mybox"
    path: str


class BoxOutput(Actuator):
    def __init__(self, options: BoxOptions) -> None:
        self.path = Path(options.path)
        self.description = f"my box ({options.path})"

    async def open(self) -> None:
        if not self.path.parent.is_dir():
            raise DeviceError(f"{self.description}: the box is not there")

    async def close(self) -> None:
        return None

    def sent_voltage(self, voltage_v: float) -> float:
        if not math.isfinite(voltage_v):
            raise ValueError(f"{self.description}: {voltage_v} is not a voltage")
        count = round(voltage_v / STEP_V)
        if self.limits_v is not None:
            low, high = self.limits_v
            if count * STEP_V > high + 1e-12:
                count = math.floor(high / STEP_V + 1e-9)
            elif count * STEP_V < low - 1e-12:
                count = math.ceil(low / STEP_V - 1e-9)
        if not 0 <= count * STEP_V <= FULL_SCALE_V + 1e-12:
            raise ValueError(f"{self.description}: {voltage_v:g} V is outside 0..{FULL_SCALE_V:g} V")
        return round(count * STEP_V, 6)

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        sent = BoxOutput.sent_voltage(self, voltage_v)  # what is written, whatever a subclass says
        try:
            with self.path.open("a") as out:
                out.write(json.dumps({"voltage_v": sent}) + "\\n")
        except OSError as error:
            raise DeviceError(f"{self.description}: {error}") from error

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        try:
            lines = self.path.read_text().splitlines()
        except OSError as error:
            raise DeviceError(f"{self.description}: {error}") from error
        return ("voltage_v", float(json.loads(lines[-1])["voltage_v"])) if lines else None


class LiarOutput(BoxOutput):
    def sent_voltage(self, voltage_v: float) -> float:
        return super().sent_voltage(voltage_v) + 0.002  # two counts off what command() writes


class BoxPlugin(DriverPlugin):
    name = "mybox"
    config_model = SensorConfig
    actuator_model = BoxOptions
    output = BoxOutput

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        return []

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        assert isinstance(config, BoxOptions)
        return self.output(config)


class LiarPlugin(BoxPlugin):
    name = "liarbox"
    output = LiarOutput


PLUGIN = BoxPlugin()
LIAR = LiarPlugin()
'''

#: appended to the README's test file: the same rig on the lying box
LIAR_TESTS_SOURCE = '''

class LiarBoxRig(MyBoxRig):
    kind = "liarbox"

    def options(self):
        return {"kind": "liarbox", "path": str(self.path)}


class TestLiarBox(ActuatorContract):
    rig = LiarBoxRig
'''


def readme_lab_test_file() -> str:
    """The README's example of a lab's test file (the python block that subclasses ``ActuatorContract``)."""
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), flags=re.DOTALL)
    [block] = [b for b in blocks if "(ActuatorContract):" in b]
    return block


def write_lab(root: Path) -> tuple[Path, Path]:
    """The lab's installed package (a module and its dist-info) and its tests folder."""
    site = root / "site"
    info = site / "nanodrift_mybox-0.0.dist-info"
    info.mkdir(parents=True)
    (site / "mybox.py").write_text(textwrap.dedent(PLUGIN_SOURCE))
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: nanodrift-mybox\nVersion: 0.0\n")
    (info / "entry_points.txt").write_text(f"[{registry.GROUP}]\nmybox = mybox:PLUGIN\nliarbox = mybox:LIAR\n")
    tests = root / "lab_tests"
    tests.mkdir()
    (tests / "pytest.ini").write_text("[pytest]\n")  # the lab's own configuration, not nanodrift's
    (tests / "test_mybox_contract.py").write_text(readme_lab_test_file() + textwrap.dedent(LIAR_TESTS_SOURCE))
    return site, tests


def outcomes(summary: str, cls: str) -> dict[str, str]:
    """check name -> PASSED/FAILED/SKIPPED, from ``-rA``'s short summary lines of test class ``cls``."""
    found = {}
    for line in summary.splitlines():
        word, _, rest = line.partition(" ")
        if word in ("PASSED", "FAILED") and f"::{cls}::" in rest:
            found[rest.split("::")[-1].split(" ")[0]] = word
    return found


def test_a_lab_runs_the_kit_on_its_own_plugin_and_a_lying_plugin_fails_naming_the_check(tmp_path: Path) -> None:
    site, tests = write_lab(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(site)}
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:cacheprovider", "-p", "no:xdist",
                             str(tests)], cwd=tests, env=env, capture_output=True, text=True, timeout=120)
    out = result.stdout
    assert result.returncode == 1, out + result.stderr  # some checks failed: the liar's

    honest = outcomes(out, "TestMyBox")
    assert set(honest.values()) == {"PASSED"}, out
    assert {"test_the_device_holds_sent_voltage_after_each_command", "test_read_back_after_a_command_is_what_was_sent",
            "test_nothing_outside_limits_v_reaches_the_device",
            "test_a_device_that_is_gone_is_a_device_error_and_a_reopen_recovers"} <= set(honest), out
    assert "mybox: one output per box" in out, out  # the multi-output checks, skipped with the rig's reason
    assert "test_a_value_the_device_cannot_represent_is_a_value_error_and_nothing_is_written" in honest, out

    liar = outcomes(out, "TestLiarBox")
    assert liar["test_the_device_holds_sent_voltage_after_each_command"] == "FAILED", out
    assert liar["test_read_back_after_a_command_is_what_was_sent"] == "FAILED", out
    assert "assert ('voltage_v', 3.333) ==" in out, out  # the kit's asserts are rewritten: the values compared show
    assert ("FAILED test_mybox_contract.py::TestLiarBox::test_the_device_holds_sent_voltage_after_each_command"
            in out), out


def test_the_emulators_import_without_pytest_and_the_kit_is_not_loaded_with_them() -> None:
    """``nanodrift.drivers.testing`` works where pytest is not installed; only the kit needs it."""
    code = ("import sys; sys.modules['pytest'] = None\n"
            "import nanodrift.drivers.testing as t\n"
            "from nanodrift.drivers.testing import FakeGcsController, ModbusTestServer\n"
            "assert 'nanodrift.drivers.testing.contract' not in sys.modules\n"
            "try:\n    import nanodrift.drivers.testing.contract\nexcept ImportError:\n    print('kit needs pytest')\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "kit needs pytest"
