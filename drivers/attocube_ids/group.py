"""The axes of one attocube IDS read as a sensor group: one connection, one poll for every configured axis.

Each poll asks, with the method names and result layouts of attocube's published API (the vendor's
``attocube-systems/IDS-APIs``: ``IDS_displacement_getMeasurementEnabled.m``, ``..._getAxisSignalQuality.m``,
``..._getAxisDisplacement.m``, ``IDS_system_getCurrentMode.m``, ``IDS_system_getSystemError.m``; the same
calls as its ``IDS`` python package):

1. ``com.attocube.ids.displacement.getMeasurementEnabled`` -> ``[errNo, enabled]``: with the measurement
   stopped no axis has a displacement, so every channel is a fault naming the device's state
   (``com.attocube.ids.system.getCurrentMode`` -> ``[errNo, mode]``: "system idle", "optics alignment
   running", ...) and, when it has one, the error that stopped it (``com.attocube.ids.system.getSystemError``
   -> ``[errNo]``, "errors occurred while starting and running measurements");
2. per axis, ``com.attocube.ids.displacement.getAxisSignalQuality`` (axis) -> ``[warningNo, contrast,
   baseline]`` (contrast in permille of the interference signal during a running measurement; the API notes
   it is updated only when a displacement is measured, so it judges a moving stage's signal best);
3. per axis, ``com.attocube.ids.displacement.getAxisDisplacement`` (axis) -> ``[warningNo, displacement]``
   in picometres, given in micrometres.

A non-zero warning number, or a contrast below ``min_contrast_permille``, is a fault for that axis alone
naming it (the warning's text from ``com.attocube.system.errorNumberToString``). An error number on
``getMeasurementEnabled``, a JSON-RPC error, silence or an answer of another shape: :class:`DeviceError`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from nanodrift.drivers.attocube_ids.config import IdsSensorConfig
from nanodrift.drivers.attocube_ids.rpc import IdsRpc
from nanodrift.drivers.base import Clock, DeviceError, Reading, SensorGroup

MEASUREMENT_ENABLED = "com.attocube.ids.displacement.getMeasurementEnabled"
CURRENT_MODE = "com.attocube.ids.system.getCurrentMode"
SYSTEM_ERROR = "com.attocube.ids.system.getSystemError"
SIGNAL_QUALITY = "com.attocube.ids.displacement.getAxisSignalQuality"
DISPLACEMENT = "com.attocube.ids.displacement.getAxisDisplacement"
ERROR_TEXT = "com.attocube.system.errorNumberToString"
UM_PER_PM = 1e-6


def _number(value: Any, where: str, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise DeviceError(f"{where}: expected {what} as a number, got {value!r}")
    return float(value)


def _fields(result: list[Any], count: int, where: str, shape: str) -> list[Any]:
    if len(result) < count:
        raise DeviceError(f"{where}: expected a result {shape}, got {result!r}")
    return result


def _first_text(result: list[Any], default: str) -> str:
    return next((item for item in result if isinstance(item, str)), default)


class IdsGroup(SensorGroup):
    def __init__(self, channels: Sequence[IdsSensorConfig], clock: Clock) -> None:
        first = channels[0]
        self.channels = list(channels)
        self.clock = clock
        self.set_channels(channels)
        per_call_s = min(c.timeout_s for c in channels)
        self.rpc = IdsRpc(first.host, first.port, per_call_s)
        # one poll: the state, and up to four calls per axis (a warning asks its text), each bounded by timeout_s
        self.timeout_s = per_call_s * (2 + 4 * len(channels))

    def __repr__(self) -> str:
        return f"IdsGroup({self.rpc.endpoint}, axes {[c.ids_axis for c in self.channels]})"

    async def open(self) -> None:
        await self.rpc.connect()
        await self._measurement_enabled()  # proves it is an IDS answering its API, not just an open port

    async def close(self) -> None:
        await self.rpc.close()

    async def _measurement_enabled(self) -> bool:
        where = f"attocube IDS {self.rpc.endpoint}: {MEASUREMENT_ENABLED}"
        result = _fields(await self.rpc.call(MEASUREMENT_ENABLED), 2, where, "[errNo, enabled]")
        if result[0] != 0:
            raise DeviceError(f"{where}: error {result[0]}: {await self._text(result[0])}")
        if not isinstance(result[1], bool):
            raise DeviceError(f"{where}: expected enabled as true or false, got {result[1]!r}")
        return result[1]

    async def _text(self, number: Any) -> str:
        """The device's own text for an error or warning number (the number alone when it has none)."""
        try:
            result = await self.rpc.call(ERROR_TEXT, [0, number])
        except DeviceError:
            return "(no text from the device)"
        return _first_text(result, "(no text from the device)")

    async def _why_stopped(self) -> str:
        """The device's state, and the error that stopped its measurement when it reports one."""
        mode = _first_text(await self.rpc.call(CURRENT_MODE), "unknown")  # [errNo, mode] (API 2) or [mode]
        why = f"mode {mode!r}"
        error = (await self.rpc.call(SYSTEM_ERROR))[0]
        if error != 0:
            why += f"; system error {error}: {await self._text(error)}"
        return why

    async def read(self) -> dict[str, Reading]:
        if not await self._measurement_enabled():
            why = await self._why_stopped()
            t = self.clock.now()
            return {c.name: Reading.fault(t, f"attocube IDS {self.rpc.endpoint} axis {c.ids_axis}: measurement "
                                             f"not running ({why})", "um") for c in self.channels}
        return {config.name: await self._read_axis(config) for config in self.channels}  # one axis after another

    async def _read_axis(self, config: IdsSensorConfig) -> Reading:
        axis = config.ids_axis
        where = f"attocube IDS {self.rpc.endpoint} axis {axis}"
        quality = _fields(await self.rpc.call(SIGNAL_QUALITY, [axis]), 3, f"{where}: {SIGNAL_QUALITY}",
                          "[warningNo, contrast, baseline]")
        contrast = _number(quality[1], f"{where}: {SIGNAL_QUALITY}", "the contrast (permille)")
        moved = _fields(await self.rpc.call(DISPLACEMENT, [axis]), 2, f"{where}: {DISPLACEMENT}",
                        "[warningNo, displacement]")
        displacement_pm = _number(moved[1], f"{where}: {DISPLACEMENT}", "the displacement (pm)")
        t = self.clock.now()
        for warning, method in ((quality[0], SIGNAL_QUALITY), (moved[0], DISPLACEMENT)):
            if warning != 0:
                return Reading.fault(t, f"{where}: warning {warning} from {method}: {await self._text(warning)}", "um")
        if contrast < config.min_contrast_permille:
            return Reading.fault(t, f"{where}: bad signal: contrast {contrast:g} permille, below "
                                    f"min_contrast_permille = {config.min_contrast_permille}", "um")
        sign = -1.0 if config.invert else 1.0
        return Reading(value=sign * displacement_pm * UM_PER_PM + config.offset_um, t=t, unit="um")
