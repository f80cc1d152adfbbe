"""The EPICS Channel Access bridge of ``nanodrift ioc``: each axis of a cell as a motor-like set of PVs.

PVs (``<P>`` the ``--pv-prefix``; a cell of several axes: ``<P><cell>:<axis>:...``): ``SP``, ``RBV``,
``DMOV``, ``STOP``, ``STATE``, ``VOLT``, ``SIGMA``, ``MSG``, as :class:`AxisPVs` declares them and the
README's table (*Bluesky and EPICS*) documents them: a put to ``SP`` moves the axis (the others at their
last setpoints); one refused, or not answered within ``--answer-timeout``, fails (``ECA_PUTFAIL``,
``SP`` in WRITE/MAJOR alarm), leaves ``DMOV`` 1 and says why in ``MSG``.

Why caproto: it is pure Python (pip-installable, an asyncio server), so the bridge installs with
``pip install 'nanodrift[epics]'`` on any machine that runs nanodrift and runs in CI. pythonSoftIOC
embeds a compiled EPICS base (an IOC shell, records and their database), which is more than a bridge of a
few soft PVs needs and ties the install to binary wheels of EPICS.

Everything a PV shows goes through one queue, applied in order by one task, so a ``DMOV`` 0 is always
published before the 1 of the same move, and a value from Zenoh's threads reaches caproto on its loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from caproto import AlarmSeverity, AlarmStatus, ChannelType
from caproto.asyncio.server import Context
from caproto.server import PVGroup, pvproperty

from nanodrift.async_moves import ANSWER_TIMEOUT_S, AsyncMoves, Moving
from nanodrift.cell_view import CellView, Measured, axis_value, cell_state
from nanodrift.client import Client, MoveEnded, Refused

__all__ = ["AxisPVs", "CellBridge", "serve", "state_of"]

#: how often each cell's ``status`` is asked for (``STATE``)
STATUS_PERIOD_S = 1.0
#: the longest move a put may start (a ``done`` later than this ends the move ``MSG``: timeout)
MOVE_TIMEOUT_S = 600.0
#: ``MSG``'s length: a char waveform of up to 256 bytes
MSG_MAX_BYTES = 256


def state_of(status: Mapping[str, Any]) -> str:
    """``STATE``: ``fault`` when the cell's outputs are faulted, else ``nanodrift status``'s state column."""
    actuator = status.get("actuator")
    if isinstance(actuator, dict) and actuator.get("state") == "fault":
        return "fault"
    return cell_state(status)


def _message(text: str) -> str:
    """``text`` as ``MSG`` holds it: whole UTF-8 characters and a terminating NUL within 256 bytes (C's string,
    as char waveforms carry text; never zero-length, which some CA clients drop from monitors)."""
    return text.encode("utf-8")[:MSG_MAX_BYTES - 1].decode("utf-8", "ignore") + "\0"


class AxisPVs(PVGroup):
    """One axis' PVs under ``prefix`` (``<P><cell>:`` or ``<P><cell>:<axis>:``)."""

    async def _put_setpoint(self, instance: Any, value: float) -> float:
        await self.bridge.put_setpoint(self.axis, float(value))
        return value

    async def _put_stop(self, instance: Any, value: int) -> int:
        if value:
            await self.bridge.stop(self.axis)
        return 0

    SP = pvproperty(put=_put_setpoint, value=math.nan, dtype=float, record="ao", units="um", precision=4,
                    doc="target (um); a put moves the axis")
    RBV = pvproperty(value=math.nan, dtype=float, record="ai", units="um", precision=4, read_only=True,
                     doc="measured position, else the target of the last reached or stopped move (um)")
    DMOV = pvproperty(value=1, dtype=int, read_only=True, doc="1 when no move is in flight")
    STOP = pvproperty(put=_put_stop, value=0, dtype=int,
                      doc="a put of 1 stops the cell: every output holds where it is")
    STATE = pvproperty(value="offline", dtype=ChannelType.STRING, read_only=True, doc="the cell's status state")
    VOLT = pvproperty(value=math.nan, dtype=float, record="ai", units="V", precision=5, read_only=True,
                      doc="the voltage the latest command asks for")
    SIGMA = pvproperty(value=math.nan, dtype=float, record="ai", units="um", precision=4, read_only=True,
                       doc="the latest command's standard uncertainty (um)")
    MSG = pvproperty(value="\0", dtype=ChannelType.CHAR, max_length=MSG_MAX_BYTES, string_encoding="utf-8",
                     read_only=True, doc="the last refusal's or failure's text; empty after a reached move")

    def __init__(self, prefix: str, *, bridge: CellBridge, axis: str) -> None:
        self.bridge = bridge
        self.axis = axis
        super().__init__(prefix)


class CellBridge:
    """One cell's PVs and what moves them: a put to ``SP`` is a move (:class:`~nanodrift.async_moves.AsyncMoves`:
    no thread waits for its ``done``), a put to ``STOP`` a stop on a worker no move occupies; the broadcasts and
    ``status`` fill the rest. ``answer_timeout_s``: how long a put waits for the daemon's answer before it fails."""

    def __init__(self, client: Client, view: CellView, pv_prefix: str, *,
                 answer_timeout_s: float = ANSWER_TIMEOUT_S) -> None:
        self.client = client
        self.view = view
        self.moves = AsyncMoves(client, axes=len(view.axes), answer_timeout_s=answer_timeout_s)
        self.cell = view.cell
        base = f"{pv_prefix}{self.cell}:"
        self.groups = {axis: AxisPVs(f"{base}{axis}:" if view.multi_axis else base, bridge=self, axis=axis)
                       for axis in view.axes}
        self._moving: dict[str, int] = {}  # axis -> the move (token) it is in
        self._tokens = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._updates: asyncio.Queue[tuple[Any, Any]] = asyncio.Queue()
        self._refresh = asyncio.Event()
        self._followers: set[asyncio.Future[None]] = set()

    @property
    def pvdb(self) -> dict[str, Any]:
        return {name: pv for group in self.groups.values() for name, pv in group.pvdb.items()}

    # --- the tasks --------------------------------------------------------------------------------

    async def run(self) -> None:
        """Apply updates and keep ``STATE`` fresh until cancelled."""
        self._loop = asyncio.get_running_loop()
        self.view.add_listener(self._from_zenoh)
        if command := self.view.command():
            self._show_command(command)
        for axis in self.view.axes:
            self._on_broadcast("position", axis, self.view.position(axis))  # None (no sample yet): nothing
        await asyncio.gather(self._apply_updates(), self._poll_status())

    async def _apply_updates(self) -> None:
        while True:
            pv, value = await self._updates.get()
            await pv.write(value, verify_value=False)  # an internal update: no putter, no move

    async def _poll_status(self) -> None:
        while True:
            try:
                state = state_of(await self.moves.status(timeout_s=2.0))
            except (TimeoutError, ValueError):
                state = "offline"
            for group in self.groups.values():
                self._post(group.STATE, state)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._refresh.wait(), STATUS_PERIOD_S)
            self._refresh.clear()

    def _post(self, pv: Any, value: Any) -> None:
        self._updates.put_nowait((pv, value))

    # --- the broadcasts (from Zenoh's threads, handed to the loop) ---------------------------------

    def _from_zenoh(self, kind: str, axis: str, value: Any) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._on_broadcast, kind, axis, value)

    def _on_broadcast(self, kind: str, axis: str, value: Any) -> None:
        if kind == "command":
            self._show_command(value)
        elif kind == "position" and isinstance(value, Measured):
            self._post(self.groups[axis].RBV, value.value_um)

    def _show_command(self, doc: Mapping[str, Any]) -> None:
        for axis, group in self.groups.items():
            setpoint = axis_value(doc, f"{axis}_um", axis)
            if math.isfinite(setpoint):
                self._post(group.SP, setpoint)
            self._post(group.VOLT, axis_value(doc, "voltage_v", axis))
            self._post(group.SIGMA, axis_value(doc, "q_sigma_um", axis))

    # --- puts ------------------------------------------------------------------------------------

    async def put_setpoint(self, axis: str, value: float) -> None:
        """Move ``axis`` to ``value``; returns once the daemon answered (``DMOV`` 0). Raises (the put fails,
        ``SP`` in alarm, ``MSG`` says why) on a refusal, or when no answer comes within the answer timeout."""
        group = self.groups[axis]
        try:
            moving = await self.moves.move(self.view.request({axis: value}))
        except (ValueError, Refused, TimeoutError, ConnectionError, RuntimeError) as error:  # nothing moves
            self._post(group.MSG, _message(str(error)))
            self._refresh.set()  # a refusal for a stale sensor or a faulted output shows in STATE now
            raise
        self.view.note_command(moving.command)  # the latest setpoints, before the command's broadcast arrives
        # a refused put left SP in caproto's alarm (WRITE, MAJOR); a put that moves clears it
        await group.SP.alarm.write(status=AlarmStatus.NO_ALARM, severity=AlarmSeverity.NO_ALARM)
        token = next(self._tokens)
        for other in {axis, *self._moving}:  # axes still heading to their setpoints go on in this move
            self._moving[other] = token
        self._post(group.DMOV, 0)
        follower = asyncio.ensure_future(self._follow(moving, token))
        self._followers.add(follower)  # held until it ends (the loop keeps only weak references to tasks)
        follower.add_done_callback(self._followers.discard)

    async def _follow(self, moving: Moving, token: int) -> None:
        """The end of one move: ``DMOV`` 1 and ``MSG`` on the axes still in it (a newer move took the others)."""
        text, ended = "", "reached"
        try:
            await moving.ended(MOVE_TIMEOUT_S)
        except MoveEnded as error:
            text, ended = str(error), error.state
        except (Refused, TimeoutError, ConnectionError, RuntimeError) as error:
            text, ended = str(error), "failed"
        axes = [axis for axis, owner in self._moving.items() if owner == token]
        for axis in axes:
            del self._moving[axis]
            group = self.groups[axis]
            if ended in ("reached", "stopped") and not self.view.axes[axis].position_sensor:
                target = moving.command.target
                self._post(group.RBV, target[axis] if isinstance(target, Mapping) else target)
            self._post(group.MSG, _message(text))
            self._post(group.DMOV, 1)

    async def stop(self, axis: str) -> None:
        """``stop`` the cell (every output holds where it is); raises when the daemon does not answer."""
        try:
            await self.moves.stop()
        except (Refused, TimeoutError) as error:
            self._post(self.groups[axis].MSG, _message(str(error)))
            raise

    def close(self) -> None:
        self.moves.close()
        self.view.close()
        self.client.close()


async def serve(bridges: Sequence[CellBridge], on_ready: Callable[[], None] = lambda: None) -> None:
    """Serve every bridge's PVs over Channel Access until cancelled (interfaces and ports: caproto's
    ``EPICS_CAS_INTF_ADDR_LIST``, ``EPICS_CA_SERVER_PORT``...); ``on_ready`` once the server listens."""
    pvdb = {name: pv for bridge in bridges for name, pv in bridge.pvdb.items()}
    context = Context(pvdb)

    async def started(async_lib: Any) -> None:
        on_ready()

    await asyncio.gather(context.run(startup_hook=started), *(bridge.run() for bridge in bridges))
