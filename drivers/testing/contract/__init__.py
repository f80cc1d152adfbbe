"""The plugin contract kit: the checks every driver plugin must pass, as pytest test classes a lab imports.

nanodrift runs its own plugins (``simulated``, ``modbus``, ``serial_line``, ``attocube_ids``, ``dcon``) through
exactly these classes (``tests/drivers/test_actuator_contract.py``, ``tests/drivers/test_sensor_contract.py``);
a lab runs its plugin through them in its own repository. A rig says how to build the plugin's device emulator and how
to read what the device actually received; the contract class holds the checks::

    # tests/test_mybox_contract.py, in the lab's repository (its plugin installed: pip install -e .)
    from nanodrift.drivers.testing.contract import ActuatorContract, ActuatorRig

    class MyBoxRig(ActuatorRig):
        kind = "mybox"                            # its name in the nanodrift.drivers entry points
        limit_case = ((0.0, 5.0), 5.0, 5.0)
        multi_output_unsupported = "one output per box"

        def options(self):                        # its [actuator] table
            return {"kind": "mybox", "path": str(self.tmp_path / "out.txt")}

        async def held_v(self): ...               # read from the emulator, never from the actuator
        def written_v(self): ...
        async def refuse_writes(self): ...
        async def gone(self): ...
        async def back(self): ...

    class TestMyBox(ActuatorContract):
        rig = MyBoxRig

pytest collects ``TestMyBox`` (the kit's own classes do not start with ``Test``, so importing them
collects nothing) and runs every check against ``MyBoxRig``; a failure names the check
(``TestMyBox::test_the_device_holds_sent_voltage_after_each_command``). A check a rig cannot take part
in (a device that cannot fail, a device that takes any value, a single output) is skipped with the
rig's reason. Every assertion on what was written looks at the emulator's side, never at the
actuator's own account.

The contracts themselves, check by check, are in :mod:`nanodrift.drivers.testing.contract.checks`.

This package imports pytest: it is for test suites, and ``nanodrift.drivers.testing`` does not import
it (the emulators work without pytest).
"""

import pytest

# before the checks are imported: pytest rewrites their asserts (a test module's are rewritten by pytest
# itself; a helper package's only when registered), so a failed check shows what it compared
pytest.register_assert_rewrite("nanodrift.drivers.testing.contract.checks")

from nanodrift.drivers.testing.contract.checks import (  # noqa: E402
    CHECK_BOUND_S,
    COMMAND_BOUND_S,
    GAIN_V_PER_UM,
    LIMITS_V,
    TOLERANCE_V,
    ActuatorContract,
    ActuatorRig,
    OffsetClock,
    SensorContract,
    SensorRig,
)

__all__ = [
    "CHECK_BOUND_S",
    "COMMAND_BOUND_S",
    "GAIN_V_PER_UM",
    "LIMITS_V",
    "TOLERANCE_V",
    "ActuatorContract",
    "ActuatorRig",
    "OffsetClock",
    "SensorContract",
    "SensorRig",
]
