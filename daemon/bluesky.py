"""``nanodrift.bluesky.Stage``: a compensated cell as an ophyd-async device for Bluesky plans
(extra ``nanodrift[bluesky]``; README, *Bluesky and EPICS*, shows it in a plan).

Why it is built this way:

- Moving is the ``compensate`` query (in a worker thread of the device's own, bounded by the answer
  timeout), then the ``done`` event awaited on the loop (:class:`nanodrift.async_moves.AsyncMoves`), so
  ``set`` completes on ``done`` ``reached`` and fails with the client's own exceptions
  (:class:`~nanodrift.Refused`, :class:`~nanodrift.MoveEnded`): nothing polls telemetry, and no thread
  waits for a ``done``. ``stop()`` is the client's ``stop`` on a worker no move occupies (never queued behind
  moves, on asyncio's default executor or elsewhere); its ``done`` ``stopped`` ends the move.
- Readings are ophyd-async soft signals whose *getter* reads what the client last saw (the cell's latest
  ``command``, the latest position sample): a read costs no query, and a value another client caused
  (``nanodrift target``, the EPICS bridge) shows too.
- The axes are the cell's own, learned from its ``status`` when the device connects: a one-axis cell is
  one motor (readings ``<name>``, ``<name>-setpoint``, ``<name>-q_um``, ``<name>-voltage_v``,
  ``<name>-q_sigma_um``); a cell of several has one motor per axis (``stage.x``: ``<name>-x``,
  ``<name>-x-setpoint``, ...), and moving one moves the cell with the others at their last setpoints.
- The readback is the measured position where a position sensor measures the axis, else the target of
  the last move this device saw reached. After a reached move, ``set`` also waits (up to
  ``FRESH_POSITION_TIMEOUT_S``) for the first position sample taken after the ``done``, so the reading a
  plan takes next is the position after the move, not one from before it.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from bluesky.protocols import Movable, Stoppable
from ophyd_async.core import (
    AsyncStatus,
    CalculatableTimeout,
    DeviceConnector,
    SignalR,
    StandardReadable,
    soft_signal_r_and_setter,
)
from ophyd_async.core import StandardReadableFormat as Format

from nanodrift.async_moves import ANSWER_TIMEOUT_S, AsyncMoves
from nanodrift.bus.protocol import DEFAULT_PREFIX
from nanodrift.cell_view import CellView, axis_value
from nanodrift.client import Client, Command, Position

__all__ = ["Stage", "StageAxis"]

#: how long a move may take when the plan gives no timeout (``bps.mv`` gives none)
DEFAULT_MOVE_TIMEOUT_S = 60.0
#: how long a reached move waits for the position sample that follows its ``done``
FRESH_POSITION_TIMEOUT_S = 2.0


class _AxisReadings(StandardReadable):
    """The five readings of one axis, as soft signals whose getters read the cell's view."""

    readback: SignalR[float]

    def _add_readings(self, stage: Stage, axis: str) -> None:
        def reading(getter: Callable[[], float], units: str = "um", precision: int = 4) -> SignalR[float]:
            return soft_signal_r_and_setter(float, math.nan, units=units, precision=precision, getter=getter)[0]

        def command_value(key: str) -> Callable[[], float]:
            return lambda: axis_value(stage.view.command(), key, axis)

        with self.add_children_as_readables(Format.HINTED_UNCACHED_SIGNAL):
            self.readback = reading(lambda: stage.readback_um(axis))
        with self.add_children_as_readables(Format.UNCACHED_SIGNAL):
            self.setpoint = reading(command_value(f"{axis}_um"))
            self.q_um = reading(command_value("q_um"))
            self.voltage_v = reading(command_value("voltage_v"), "V", 5)
            self.q_sigma_um = reading(command_value("q_sigma_um"))

    def set_name(self, name: str, *, child_name_separator: str | None = None) -> None:
        super().set_name(name, child_name_separator=child_name_separator)
        if "readback" in self.__dict__:  # the readback reads as the motor's own name, as ophyd's motors do
            self.readback.set_name(name)


class _CellConnector(DeviceConnector):
    """Opens the client, learns the cell's axes from its ``status``, then makes the signals."""

    async def connect_real(self, device: Any, timeout: float, force_reconnect: bool) -> None:
        assert isinstance(device, Stage)
        await device.open(timeout)
        await super().connect_real(device, timeout, force_reconnect)


class Stage(_AxisReadings, Movable[Any], Stoppable):
    """A nanodrift cell: ``set`` a position (µm; a mapping by axis in a cell of several), read it, ``stop`` it.

    ``endpoint`` and ``zenoh_config``, ``prefix``: as :class:`nanodrift.Client`. Connect it the ophyd-async
    way (``init_devices()`` or ``await stage.connect()``); :meth:`close` ends its Zenoh session.
    """

    def __init__(self, endpoint: str | list[str] | None, cell: str, *, name: str = "", prefix: str = DEFAULT_PREFIX,
                 zenoh_config: str | Path | None = None) -> None:
        self.endpoint = endpoint
        self.cell = cell
        self.prefix = prefix
        self.zenoh_config = zenoh_config
        self._client: Client | None = None
        self._view: CellView | None = None
        self._moves: AsyncMoves | None = None
        self._reached: dict[str, float] = {}  # axis -> target of the last move seen reached
        self._in_flight = 0  # moves of this device not yet ended (stop() stops only while there is one)
        super().__init__(name=name, connector=_CellConnector())

    # --- connecting -----------------------------------------------------------------------------------

    async def open(self, timeout: float) -> None:
        """Open the client and the view of the cell, and make one motor per axis (or this one's signals)."""
        if self._view is not None:
            return
        self._client, view, self._moves = await asyncio.to_thread(self._open_view, timeout)
        self._view = view
        if view.multi_axis:
            with self.add_children_as_readables():
                for axis in view.axes:
                    setattr(self, axis, StageAxis(self, axis))
        else:
            self._add_readings(self, "x")
        self.set_name(self.name)

    def _open_view(self, timeout: float) -> tuple[Client, CellView, AsyncMoves]:
        client = Client(self.endpoint, self.cell, zenoh_config=self.zenoh_config, prefix=self.prefix)
        try:
            view = CellView.open(client, timeout_s=timeout)
            return client, view, AsyncMoves(client, axes=len(view.axes))
        except BaseException:
            client.close()
            raise

    def close(self) -> None:
        """End the Zenoh session (a move still waiting raises)."""
        if self._moves is not None:
            self._moves.close()
        if self._view is not None:
            self._view.close()
        if self._client is not None:
            self._client.close()

    @property
    def view(self) -> CellView:
        if self._view is None:
            raise RuntimeError(f"stage {self.name or self.cell!r} is not connected (init_devices() or await connect())")
        return self._view

    @property
    def client(self) -> Client:
        self.view  # noqa: B018  (the same "not connected" error)
        assert self._client is not None
        return self._client

    @property
    def moves(self) -> AsyncMoves:
        self.view  # noqa: B018  (the same "not connected" error)
        assert self._moves is not None
        return self._moves

    # --- moving ---------------------------------------------------------------------------------------

    @AsyncStatus.wrap
    async def set(self, value: float | Mapping[str, float], timeout: CalculatableTimeout = "CALCULATE_TIMEOUT") -> None:
        """Move to ``value``: done on ``done`` ``reached``; failed with :class:`~nanodrift.Refused` or
        :class:`~nanodrift.MoveEnded` (stopped, superseded, failed) otherwise."""
        if isinstance(value, Mapping):
            await self.move(dict(value), timeout)
        elif self.view.multi_axis:
            raise ValueError(f"cell {self.cell!r} has axes {', '.join(self.view.axes)}: move it with a mapping "
                             f"({{'x': ..., 'y': ...}}) or move one axis (stage.x)")
        else:
            await self.move({"x": float(value)}, timeout)

    async def move(self, changes: Mapping[str, float], timeout: CalculatableTimeout = "CALCULATE_TIMEOUT") -> Command:
        """Move the axes in ``changes``, the others held at their last setpoints; the reached command."""
        view = self.view
        target: Position = view.request(changes)
        timeout_s = DEFAULT_MOVE_TIMEOUT_S if timeout == "CALCULATE_TIMEOUT" or timeout is None else float(timeout)
        deadline = asyncio.get_running_loop().time() + timeout_s
        self._in_flight += 1
        try:
            moving = await self.moves.move(target, answer_timeout_s=min(timeout_s, ANSWER_TIMEOUT_S))
            view.note_command(moving.command)  # the latest setpoints, before the command's broadcast arrives
            command = await moving.ended(max(deadline - asyncio.get_running_loop().time(), 0.0))
        finally:
            self._in_flight -= 1
        done_t = float(command.done["t"]) if command.done and isinstance(command.done.get("t"), int | float) else 0.0
        moved = command.target if isinstance(command.target, Mapping) else {"x": float(command.target)}
        self._reached.update(moved)
        sensed = [axis for axis in moved if view.axes[axis].position_sensor]
        await asyncio.gather(*(asyncio.to_thread(view.wait_position, axis, done_t, FRESH_POSITION_TIMEOUT_S)
                               for axis in sensed))
        return command

    async def stop(self, success: bool = True) -> None:
        """While a move of this device is in flight: every output of the cell holds where it is and the move
        fails ``stopped``. Otherwise nothing: the RunEngine calls ``stop()`` on every device it moved at the end
        of each plan, and a move another client started since is not this plan's to stop."""
        if self._in_flight:
            await self.moves.stop()

    def readback_um(self, axis: str) -> float:
        """The measured position where a sensor measures ``axis``, else the last reached target (nan: none yet)."""
        view = self.view
        if view.axes[axis].position_sensor:
            measured = view.position(axis)
            return measured.value_um if measured is not None else math.nan
        return self._reached.get(axis, math.nan)


class StageAxis(_AxisReadings, Movable[float], Stoppable):
    """One axis of a cell of several (``stage.x``): moving it moves the cell with the other axes at their
    last setpoints; stopping it stops the cell."""

    def __init__(self, stage: Stage, axis: str) -> None:
        self._move = stage.move  # the stage's methods, not the stage: a Device attribute would be a child
        self._stop = stage.stop
        self.axis = axis
        self._add_readings(stage, axis)
        super().__init__()

    @AsyncStatus.wrap
    async def set(self, value: float, timeout: CalculatableTimeout = "CALCULATE_TIMEOUT") -> None:
        """Move this axis to ``value`` µm (the others held)."""
        await self._move({self.axis: float(value)}, timeout)

    async def stop(self, success: bool = True) -> None:
        await self._stop(success)
