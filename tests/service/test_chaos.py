"""Chaos: random interleavings of targets, reloads, clock steps, device and sensor faults against one real daemon.

A hypothesis state machine (:class:`helpers.chaos.ChaosMachine`, shared with ``test_chaos_serial.py``)
drives one ``nanodrift run`` process per example, its output an emulated Modbus module (pymodbus' TCP server
on 127.0.0.1, on a thread of this process) that stamps every write as it arrives and can fail writes, answer
late or lie when read back; its temperatures come from the test-only ``file`` sensor plugin. Rules: targets
(valid, outside the workspace, malformed), valid and invalid reloads (``v_min``/``v_max``,
``max_slew_um_per_s``, ``volts_per_um``; an unknown key, bad TOML, inconsistent limits), wall-clock steps
(±600 s, ±1 day), device faults, latency and lies, temperature changes and channel faults, SIGTERM and restart.

After every step, on the device side (what the register received, decoded to volts):

1. every write that reached the module is inside the ``[v_min, v_max]`` in force when it arrived (within a
   reload's window, from SIGHUP to its ``reload_applied`` line, the old or the new limits);
2. once quiet, the register holds the last served command's voltage (as a count), unless the limits now in
   force forbid it (``actuator_goal_dropped``: nothing is written after it) or the module is failing; after
   a SIGTERM it holds ``safe_voltage_v`` (0 V);
3. every target got exactly one answer with its id (``command`` or ``error``, of a kind the step allows);
4. the daemon is alive, ``status`` answers and shows the limits the test believes are in force.

The suite runs 3 examples of up to 12 steps (about 10 s). The release run (~4 minutes), with every other long
test at its release size (``helpers.budget``)::

    NANODRIFT_LONG_TESTS=1 python -m pytest -q -n 0 tests/service/test_chaos.py

(60 examples of up to 40 steps; ``NANODRIFT_CHAOS_EXAMPLES`` and ``NANODRIFT_CHAOS_STEPS`` set them.)

``NANODRIFT_CHAOS_SHRINK=0`` reports the first failing sequence unshrunk (each shrink step starts a daemon).

Found by it and fixed: a command whose write failed was not written again once the module worked again
(the regression test at the end replays the minimal sequence).
"""

from __future__ import annotations

from helpers.budget import sized
from helpers.chaos import ChaosMachine, Limits, chaos_settings

EXAMPLES = sized("NANODRIFT_CHAOS_EXAMPLES", 3, 60)
STEPS = sized("NANODRIFT_CHAOS_STEPS", 12, 40)

ChaosMachine.TestCase.settings = chaos_settings(EXAMPLES, STEPS)
TestChaos = ChaosMachine.TestCase


def test_a_command_whose_write_failed_is_written_once_the_module_works_again() -> None:
    """The minimal sequence the chaos machine found: one target served while the module fails its writes, the
    module works again; once quiet the register must hold that command (it keeps 0 V)."""
    machine = ChaosMachine()
    try:
        machine.start_daemon(Limits(-2.0, 2.5, 0.0, 0.01))
        machine.check()
        machine.module_starts_failing_writes()
        machine.check()
        machine.send_targets([("valid", 0.0)])
        machine.check()
        machine.module_works_again()
        machine.check()
    finally:
        machine.teardown()
