"""Real Modbus peers for testing a driver: pymodbus' own servers on 127.0.0.1 and on a pty pair.

- :class:`ModbusTestDevice`: one device's register map (input and holding ranges; outside them,
  exception 2), with hooks a test uses to misbehave (``fail_with``, ``fail_writes_with``,
  ``refuse_writes``, ``write_delay_s``, ``on_read``/``on_write``) and the requests it saw
  (``reads``, ``writes``);
- :class:`ModbusTestServer`: pymodbus' TCP server (or RTU on a serial port) for those devices,
  stoppable and restartable on the same port (the values survive, like a module's inputs);
- :class:`PtyNullModem`: two ptys back to back, for RTU over a "serial cable";
- :func:`tcp_context`, :func:`device_registers`, :func:`crc16_modbus`; :func:`free_port` (from
  :mod:`nanodrift.drivers.local_port`: a port below the kernel's ephemeral range, which no outgoing connection takes).

Also runnable as a separate process (a test kills and restarts it)::

    python -m nanodrift.drivers.testing.modbus_server --port 15020 --values 21.5,22.0,...   # input registers 0.., x0.1
"""

from __future__ import annotations

import argparse
import asyncio
import os
import select
import signal
import threading
import tty
from collections.abc import Callable, Iterable, Sequence

from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerRTU, FramerType
from pymodbus.server import ModbusBaseServer, ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from nanodrift.drivers.base import DriverContext
from nanodrift.drivers.local_port import free_port as free_port  # re-exported: the emulators' users pick ports with it
from nanodrift.drivers.modbus.codec import DATA_TYPES, encode
from nanodrift.drivers.modbus.config import ModbusHubConfig

FC_READ_HOLDING = 3
FC_READ_INPUT = 4


def _ranges(ranges: Iterable[tuple[int, int]]) -> list[SimData]:
    return [SimData(address=start, count=count, values=0, datatype=DataType.REGISTERS) for start, count in ranges]


class ModbusTestDevice:
    """A device's register map; registers outside the given ranges answer exception 2."""

    def __init__(
        self,
        device_id: int = 1,
        input_ranges: Sequence[tuple[int, int]] = ((0, 32),),
        holding_ranges: Sequence[tuple[int, int]] = ((0, 32),),
    ) -> None:
        self.device_id = device_id
        self.input_ranges = tuple(input_ranges)
        self.holding_ranges = tuple(holding_ranges)
        self.fail_with: ExcCodes | None = None  # answer every read with this exception code
        self.fail_writes_with: ExcCodes | None = None  # answer every write with this exception code
        self.refuse_writes = 0  # answer the next N writes with DEVICE_FAILURE (nothing stored), then take them
        self.write_delay_s = 0.0  # answer each write this late (a slow module or gateway)
        self.reads: list[tuple[int, int, int]] = []  # (function code, address, count) per read request
        self.writes: list[tuple[int, int, list[int]]] = []  # (function code, address, values) per write request
        #: called with (address, values) before a write lands; may change ``values`` in place (a device
        #: that clamps or ignores what it is sent)
        self.on_write: Callable[[int, list[int]], None] | None = None
        self.quiet = False  # the test itself is looking (ModbusTestServer.get_registers): not a request
        #: called with (function code, first address of the block, the block's registers) before a read is
        #: answered; may change the registers in place (an emulated module measuring now)
        self.on_read: Callable[[int, int, list[int]], None] | None = None

    async def _action(self, function_code: int, _start: int, address: int, count: int,
                      _registers: list[int], set_values: object) -> ExcCodes | None:
        if set_values is None:
            if function_code in (FC_READ_HOLDING, FC_READ_INPUT) and not self.quiet:  # not a write's own echo
                self.reads.append((function_code, address, count))
                if self.on_read is not None:
                    self.on_read(function_code, _start, _registers)
            return self.fail_with
        assert isinstance(set_values, list)
        self.writes.append((function_code, address, list(set_values)))
        if self.write_delay_s > 0:
            await asyncio.sleep(self.write_delay_s)
        if self.fail_writes_with is not None:
            return self.fail_writes_with
        if self.refuse_writes > 0:
            self.refuse_writes -= 1
            return ExcCodes.DEVICE_FAILURE
        if self.on_write is not None:
            self.on_write(address, set_values)
        return None

    def sim_device(self) -> SimDevice:
        bits = [SimData(address=0, count=16, values=False, datatype=DataType.BITS)]
        return SimDevice(
            id=self.device_id,
            simdata=(list(bits), list(bits), _ranges(self.holding_ranges), _ranges(self.input_ranges)),
            action=self._action,
        )


class ModbusTestServer:
    """pymodbus' TCP (or RTU-on-a-serial-port) server, stoppable and restartable on the same port."""

    def __init__(self, devices: Sequence[ModbusTestDevice], *, port: int | None = None,
                 serial_port: str | None = None) -> None:
        self.devices = {d.device_id: d for d in devices}
        self.port = port or free_port()
        self.serial_port = serial_port
        self._server: ModbusBaseServer | None = None
        # values survive a restart, like a module's inputs
        self._values: dict[tuple[int, int, int], list[int]] = {}

    async def start(self) -> None:
        sims = [d.sim_device() for d in self.devices.values()]
        if self.serial_port:
            self._server = ModbusSerialServer(sims, framer=FramerType.RTU, port=self.serial_port,
                                              baudrate=115200, timeout=0.2)
        else:
            self._server = ModbusTcpServer(sims, address=("127.0.0.1", self.port))
        await self._server.serve_forever(background=True)
        for (device_id, fc, address), regs in self._values.items():
            await self._server.async_setValues(device_id, fc, address, regs)

    async def stop(self) -> None:
        if self._server is not None:
            await self._server.shutdown()
            self._server = None

    async def set_registers(self, device_id: int, address: int, registers: Sequence[int],
                            input_type: str = "input") -> None:
        fc = FC_READ_INPUT if input_type == "input" else FC_READ_HOLDING
        self._values[(device_id, fc, address)] = list(registers)
        if self._server is not None:
            await self._server.async_setValues(device_id, fc, address, list(registers))

    async def get_registers(self, device_id: int, address: int, count: int, input_type: str = "holding") -> list[int]:
        """What the device holds now (as a master reading it would see)."""
        assert self._server is not None
        fc = FC_READ_INPUT if input_type == "input" else FC_READ_HOLDING
        device = self.devices[device_id]
        device.quiet = True
        try:
            return [int(v) for v in await self._server.async_getValues(device_id, fc, address, count)]
        finally:
            device.quiet = False

    async def __aenter__(self) -> ModbusTestServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()


_PYMODBUS_TYPES = {name: ModbusClientMixin.DATATYPE[name.upper()] for name in DATA_TYPES}


def device_registers(value: float, data_type: str, swap: str = "none") -> list[int]:
    """What a device with that byte/word order sends (pymodbus' converter, not nanodrift.drivers.modbus.codec)."""
    regs = ModbusClientMixin.convert_to_registers(value, _PYMODBUS_TYPES[data_type],
                                                  word_order="little" if "word" in swap else "big")
    if swap in ("byte", "word_byte"):
        regs = [int.from_bytes(r.to_bytes(2, "big"), "little") for r in regs]
    return regs


def tcp_context(port: int, *, name: str = "adam", timeout_s: float = 0.5) -> DriverContext:
    return DriverContext(hubs={name: ModbusHubConfig(name=name, type="tcp", host="127.0.0.1", port=port,
                                               timeout_s=timeout_s)})


class PtyNullModem:
    """Two ptys joined back to back, like two serial ports and a null-modem cable.

    ``a`` and ``b`` are the device names (/dev/pts/N) the two ends open; a thread copies bytes
    between the masters. Both slave ends are held open here so a side closing its port never
    makes the other master read EIO.
    """

    def __init__(self) -> None:
        self._masters: list[int] = []
        self._slaves: list[int] = []
        names = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)
            self._masters.append(master)
            self._slaves.append(slave)
            names.append(os.ttyname(slave))
        self.a, self.b = names
        self._stop_r, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=self._relay, name="pty-null-modem", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        peer = {self._masters[0]: self._masters[1], self._masters[1]: self._masters[0]}
        while True:
            ready, _, _ = select.select([*self._masters, self._stop_r], [], [])
            if self._stop_r in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue
                if data:
                    os.write(peer[fd], data)

    def close(self) -> None:
        os.write(self._stop_w, b"x")
        self._thread.join(timeout=2)
        for fd in (*self._masters, *self._slaves, self._stop_r, self._stop_w):
            os.close(fd)

    def __enter__(self) -> PtyNullModem:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def crc16_modbus(frame: bytes) -> bytes:
    """CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF: pymodbus' own), low byte first as on the wire."""
    return FramerRTU.compute_CRC(frame).to_bytes(2, "big")  # the int it returns has the bytes swapped already


async def _serve_forever(port: int, values: Sequence[float], scale: float) -> None:
    device = ModbusTestDevice(1)
    server = ModbusTestServer([device], port=port)
    await server.start()
    regs = [encode(round(v / scale), "int16")[0] for v in values]
    await server.set_registers(1, 0, regs, "input")
    print(f"modbus server ready on 127.0.0.1:{port}", flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    await server.stop()


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="a Modbus TCP thermocouple module on 127.0.0.1")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--values", default="21.0,21.1,21.2,21.3,21.4,21.5,21.6,21.7",
                        help="degC for input registers 0.. (int16, x10)")
    parser.add_argument("--scale", type=float, default=0.1)
    args = parser.parse_args(argv)
    asyncio.run(_serve_forever(args.port, [float(v) for v in args.values.split(",")], args.scale))


if __name__ == "__main__":
    main()
