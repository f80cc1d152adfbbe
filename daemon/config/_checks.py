"""Checks across the daemon's own tables, once each table is valid on its own: procedure points inside
the workspace, each sensor's believable range, the model's channels against the sensors.

Each returns problem lines in the errors' form (``procedure.points: ...``), or the values the service
uses (:func:`valid_range`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from nanodrift.config._lines import sensor_where
from nanodrift.drivers.base import SensorConfig
from nanodrift.settings import ActuatorConfig, Config, ProcedureSettings


def points_problems(procedure: ProcedureSettings, actuator: ActuatorConfig) -> list[str]:
    """Calibration targets outside the workspace ``[x_min_um, x_max_um]``."""
    outside = [x for x in procedure.calibration_points if not actuator.x_min_um <= x <= actuator.x_max_um]
    if not outside:
        return []
    return [f"procedure.points: {', '.join(f'{x:g}' for x in outside)} um outside the workspace "
            f"[x_min_um, x_max_um] = [{actuator.x_min_um:g}, {actuator.x_max_um:g}]"]


#: a temperature sensor's believable range when it declares none (°C): wider than any lab and than a piezo
#: stage's rated range (at most ~150 °C), narrower than the codes a module sends for a broken thermocouple
#: (3276.7, -3276.8, 850); a lab measuring a hotter part sets valid_min/valid_max
DEFAULT_TEMPERATURE_RANGE_C = (-50.0, 150.0)
#: a position sensor's believable range when it declares none: the workspace widened by this share of
#: the stroke on each side (the stage overshoots and drifts a little beyond where targets may go)
POSITION_RANGE_MARGIN = 0.1


def valid_range(sensor: SensorConfig, workspace_um: tuple[float, float] | None) -> tuple[float, float]:
    """The values of ``sensor`` the daemon believes: its ``valid_min``/``valid_max``, each bound it leaves
    out from its role (position: the workspace with :data:`POSITION_RANGE_MARGIN`; temperature:
    :data:`DEFAULT_TEMPERATURE_RANGE_C`); unbounded for a position sensor when no workspace is known."""
    if sensor.role == "position":
        if workspace_um is None:
            default = (-math.inf, math.inf)
        else:
            margin = POSITION_RANGE_MARGIN * (workspace_um[1] - workspace_um[0])
            default = (workspace_um[0] - margin, workspace_um[1] + margin)
    else:
        default = DEFAULT_TEMPERATURE_RANGE_C
    low = sensor.valid_min if sensor.valid_min is not None else default[0]
    high = sensor.valid_max if sensor.valid_max is not None else default[1]
    return low, high


def valid_range_problems(sensors: Sequence[tuple[int, SensorConfig]], actuator: ActuatorConfig) -> list[str]:
    """A bound set against its role's default (``valid_min = 600`` with the workspace's 550 above it)."""
    problems = []
    for index, sensor in sensors:
        low, high = valid_range(sensor, actuator.workspace_um)
        if low < high:
            continue
        key = "valid_min" if sensor.valid_min is not None else "valid_max"
        problems.append(
            f"{sensor_where(index, sensor)}.{key}: the valid range would be [{low:g}, {high:g}] (the other bound "
            f"is the {sensor.role} default): no reading could be believed; set both valid_min and valid_max")
    return problems


def missing_model_channels(config: Config, channels: Sequence[str]) -> list[str]:
    """Channels the model needs that no temperature sensor of the config provides."""
    have = {s.name for s in config.sensors if s.role == "temperature"}
    return [c for c in channels if c not in have]
