"""Multi-axis cells for the daemon's tests: a hand-written :class:`CellModel`, a Modbus module in a thread.

The model is tiny on purpose (each axis: its own position, a crosstalk term, a temperature), so a test
can compute every expected command by hand (:func:`expected_cell_q`).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any

from nanodrift.drivers.testing.modbus_server import ModbusTestDevice, ModbusTestServer
from nanodrift.model.cell_model import CellModel, save_cell_model
from nanodrift.model.model import FittedTerm, Model, Training
from nanodrift.model.terms import parse_term

#: each axis' terms over every axis' position (a 1 % crosstalk from the next axis) and T1
CELL_CHANNEL_RANGES = {"T1": (21.5, 22.1), "T2": (21.6, 22.05)}


def cell_terms(axes: Sequence[str]) -> dict[str, dict[str, float]]:
    terms: dict[str, dict[str, float]] = {}
    for i, axis in enumerate(axes):
        other = axes[(i + 1) % len(axes)]
        terms[axis] = {axis: 1.0 + 0.001 * i, other: 0.01 * (i + 1), "T1": -0.5 + 0.1 * i, "1": 0.25 * i}
    return terms


def write_cell_model(path: Path, axes: Sequence[str] = ("x", "y"), max_um: float = 480.0,
                     rmse_um: float | None = None) -> CellModel:
    """A hand-made cell model (:func:`expected_cell_q` computes its q); with ``rmse_um`` its σ is that
    residual RMS, without it σ is unknown (no covariance, no fit)."""
    axes = tuple(axes)
    models = {}
    for axis, terms in cell_terms(axes).items():
        training = Training(x_range=(0.0, max_um), channel_ranges=dict(CELL_CHANNEL_RANGES), rows=100,
                            t_span_s=3600.0, position_ranges={a: (0.0, max_um) for a in axes if a != "x"})
        models[axis] = Model(terms=[FittedTerm(parse_term(name, axes), coef) for name, coef in terms.items()],
                             training=training, provenance={"source": "tests/helpers/cell_helpers.py"},
                             fit={} if rmse_um is None else {"rmse_um": rmse_um})
    model = CellModel(axes, models, {"source": "tests/helpers/cell_helpers.py"})
    save_cell_model(model, path)
    return model


def expected_cell_q(positions: dict[str, float], temps: dict[str, float]) -> dict[str, float]:
    axes = tuple(positions)
    out = {}
    for axis, terms in cell_terms(axes).items():
        q = 0.0
        for name, coef in terms.items():
            q += coef * (1.0 if name == "1" else temps[name] if name in temps else positions[name])
        out[axis] = q
    return out


class ThreadedModbus:
    """A :class:`ModbusTestServer` (TCP on 127.0.0.1) on its own thread's loop, for a daemon in a subprocess."""

    def __init__(self, device: ModbusTestDevice | None = None) -> None:
        self.device = device or ModbusTestDevice(device_id=1, holding_ranges=((0, 64),))
        self.server = ModbusTestServer([self.device])
        self.port = self.server.port
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> ThreadedModbus:
        ready = threading.Event()

        async def serve() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            await self.server.start()
            ready.set()
            await self._stop.wait()
            await self.server.stop()

        self._thread = threading.Thread(target=asyncio.run, args=(serve(),), name="modbus-module", daemon=True)
        self._thread.start()
        assert ready.wait(10), "the Modbus module did not start"
        return self

    def registers(self, address: int, count: int = 1) -> list[int]:
        """What the module's holding registers hold now."""
        assert self._loop is not None
        future: Future[Any] = asyncio.run_coroutine_threadsafe(self.server.get_registers(1, address, count),
                                                               self._loop)
        return list(future.result(5))

    def written(self, address: int) -> list[list[int]]:
        """Every value written to ``address`` (a write request's registers), in order."""
        return [values for _, start, values in list(self.device.writes) if start == address]

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(10)
