"""The ``[[sensors]]`` keys of an attocube IDS displacement interferometer axis."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import Field, FiniteFloat, model_validator

from nanodrift.drivers.base import SensorConfig


class IdsSensorConfig(SensorConfig):
    """One measurement axis of an IDS3010 (``ids_axis`` 0, 1 or 2) read over its JSON-RPC API on TCP.

    The reading is the axis' displacement since the measurement started, in um, sign-flipped when
    ``invert``, plus ``offset_um``: the stage's position in the cell's frame.

    ``axis`` (the cell's axis letter) is the core's key, as for every position sensor; ``ids_axis`` is the
    device's. Sensors naming one device (``host``, ``port``) share one connection and one poll.
    """

    kind: Literal["attocube_ids"] = "attocube_ids"
    role: Literal["position"] = "position"
    host: str = Field(min_length=1, description="the IDS's address (its web interface's)")
    port: int = Field(default=9090, gt=0, lt=65536, description="the JSON-RPC port (9090 on the IDS3010)")
    ids_axis: Literal[0, 1, 2] = Field(description="the device's measurement axis (0-based, as its API numbers them)")
    invert: bool = Field(default=False, description="the stage's +x moves towards the sensor head (the IDS "
                                                    "counts the displacement away from it): the reading's sign flips")
    offset_um: FiniteFloat = Field(default=0.0, description="added to the displacement (um): the stage's x where the "
                                                            "IDS measurement started (its displacement 0)")
    min_contrast_permille: int = Field(
        default=0, ge=0, le=1000,
        description="a signal contrast below this (getAxisSignalQuality, in permille) is a fault; 0 = trust the "
                    "device's own warnings only. Set it from the contrast your alignment reaches")

    @model_validator(mode="before")
    @classmethod
    def _position_by_default(cls, data: Any) -> Any:
        """An IDS measures a position: ``role`` may be left out (and the position defaults follow from it)."""
        if isinstance(data, Mapping) and "role" not in data:
            data = {**data, "role": "position"}
            return SensorConfig._role_defaults(data)  # type: ignore[operator]
        return data

    @property
    def device(self) -> tuple[str, int]:
        return self.host, self.port
