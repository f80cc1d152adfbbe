"""Move a real stage from a procedure the way the daemon does: publish the command on Zenoh.

The PZT controller (the paper's E-625) takes an analog voltage; in a lab, the node that drives that
analog output already applies the daemon's ``nanodrift/<cell>/command`` samples. The calibration
and validation procedures publish their steps on the same key with the same payload (``model`` is
null: a calibration step is the raw command), so the output node needs no second interface.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import zenoh

from nanodrift.bus.protocol import Keys, encode_command
from nanodrift.bus.session import session_config
from nanodrift.compensation import Command
from nanodrift.drivers.base import Actuator, DeviceError


class ZenohActuator(Actuator):
    """Publishes each step as a :class:`Command` with no model, named after its procedure."""

    def __init__(self, config: Any, procedure: str = "calibration") -> None:
        self.settings = config.zenoh
        self.key = Keys(config.cell, config.zenoh.prefix).command
        self.procedure = procedure
        self.sent = 0
        self._session: zenoh.Session | None = None
        self._publisher: zenoh.Publisher | None = None

    async def open(self) -> None:
        try:
            self._session = await asyncio.to_thread(zenoh.open, session_config(self.settings))
        except zenoh.ZError as err:
            raise DeviceError(f"cannot open the zenoh session to publish commands on {self.key}: {err}") from None
        self._publisher = self._session.declare_publisher(self.key)

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        if self._publisher is None:
            raise DeviceError(f"zenoh actuator for {self.key} is not open")
        self.sent += 1
        step = Command(id=f"{self.procedure}-{self.sent}", positions_um={"x": q_um if x_um is None else x_um},
                       q_um={"x": q_um}, voltage_v={"x": voltage_v}, temperatures_c={}, model=None, t=time.time(),
                       procedure=self.procedure)
        self._publisher.put(encode_command(step))

    async def close(self) -> None:
        publisher, session = self._publisher, self._session
        self._publisher = self._session = None
        if publisher is not None:
            publisher.undeclare()
        if session is not None:
            await asyncio.to_thread(session.close)
