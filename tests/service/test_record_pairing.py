"""A record row is one command every watched axis held (issue 26.6), for any order in which the axes settle.

The health unit itself, fed as the daemon feeds it (commands through the compensator, each axis'
interferometer readings): each command's hold is seen by x, by y, by both or by neither (a lost beam
voids that axis' window), with no ids or equal ids. Rows are paired by the unit's own command number:
one row per command both axes held, never one axis' target beside another's.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.cell_helpers import write_cell_model
from helpers.daemon_harness import TEMPS
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.calibration.residuals import Settled
from nanodrift.compensation import Compensator, Target
from nanodrift.config import parse_config
from nanodrift.drivers.base import Reading, SensorConfig
from nanodrift.logs import get_logger
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.recorder import Polled
from nanodrift.service.state import serving_state
from nanodrift.service.table import SensorTable

POSITION = {"x": "ifm_x", "y": "ifm_y"}
SETTLE_S, WINDOW_S = 3.0, 2.0


def xy_unit(tmp_path: Path) -> tuple[HealthUnit, Compensator, SensorTable]:
    config = parse_config({"health": {"settle_s": SETTLE_S, "window_s": WINDOW_S}, "sensors": [],
                           "axes": [{"name": a, "actuator": {"kind": "zenoh"}} for a in ("x", "y")]},
                          source="unit.toml")
    sensors = [SensorConfig(name=n, kind="x", max_age_s=5.0) for n in TEMPS]
    sensors += [SensorConfig(name=POSITION[a], kind="x", role="position", max_age_s=1.0) for a in ("x", "y")]
    config = config.model_copy(update={"sensors": sensors})
    config._sensor_axes = {name: axis for axis, name in POSITION.items()}  # what [[sensors]] axis = "y" says
    table = SensorTable(config.sensors)
    health = HealthUnit(config, None, get_logger("nanodrift.daemon"))
    compensator = serving_state(config, write_cell_model(tmp_path / "m.json", ("x", "y")), health, table=table)
    return health, compensator, table


@settings(max_examples=60, deadline=None)
@given(seen=st.lists(st.tuples(st.booleans(), st.booleans()), min_size=1, max_size=8),
       target_id=st.sampled_from([None, 7]))
def test_no_row_mixes_two_commands_whichever_axes_settle(tmp_path_factory: pytest.TempPathFactory,
                                                         seen: list[tuple[bool, bool]], target_id: int | None) -> None:
    """``seen[i]``: whether x's and y's interferometer read ok through command i's hold."""
    health, compensator, table = xy_unit(tmp_path_factory.mktemp("pairing"))
    rows: list[dict[str, Settled]] = []

    def record(axes: dict[str, Settled], unix_s: float, polled: Polled) -> None:
        rows.append(axes)

    health.settled_listeners.append(record)
    for i, oks in enumerate(seen):
        t, target_um = 20.0 * i, 10.0 * (i + 1)
        for name, value in TEMPS.items():
            table.update(name, Reading(value, t=t))
        compensator.observe(t, TEMPS)
        compensator.compensate(Target(target_id, {"x": target_um, "y": target_um}), t, 1.7e9 + t)
        for k in range(1, 13):  # readings every 0.5 s through the window [t + 3, t + 5] and past it
            now = t + 0.5 * k
            for axis, ok in zip(("x", "y"), oks, strict=True):
                health.on_position(now, now, target_um + 0.1, ok, channel=POSITION[axis])
        health.flush()
    held_by_both = [10.0 * (i + 1) for i, (x_ok, y_ok) in enumerate(seen) if x_ok and y_ok]
    assert [row["x"].x_um for row in rows] == held_by_both
    assert all(set(row) == {"x", "y"} and row["x"].sequence == row["y"].sequence and row["x"].x_um == row["y"].x_um
               for row in rows), rows
    assert all(row[a].residual_um == pytest.approx(0.1) for row in rows for a in row)
