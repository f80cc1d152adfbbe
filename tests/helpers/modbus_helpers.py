"""The Modbus emulators, now shipped in :mod:`nanodrift.drivers.testing.modbus_server`; re-exported for the tests.

Also runnable as a separate process (the daemon-level tests kill and restart it)::

    python tests/helpers/modbus_helpers.py --port 15020 --values 21.5,22.0,...   # input registers 0.., x0.1
"""

from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__":  # run as a script: this checkout's drivers, not an installed copy
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from nanodrift.drivers.testing.modbus_server import (
    FC_READ_HOLDING,
    FC_READ_INPUT,
    ModbusTestDevice,
    ModbusTestServer,
    PtyNullModem,
    crc16_modbus,
    device_registers,
    free_port,
    main,
    tcp_context,
)

__all__ = ["FC_READ_HOLDING", "FC_READ_INPUT", "ModbusTestDevice", "ModbusTestServer", "PtyNullModem",
           "crc16_modbus", "device_registers", "free_port", "main", "tcp_context"]

if __name__ == "__main__":
    main()
