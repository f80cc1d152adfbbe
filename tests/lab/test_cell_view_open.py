"""``CellView.open`` returns once each measured axis has its first position sample: a bridge that served
before it would refuse a move of another axis, which holds this one where it is measured ("no setpoint
known"; a loaded run's EPICS XY put). Against a scripted cell on a real Zenoh session over loopback whose
interferometer publishes its first sample only once a subscriber listens.
"""

from __future__ import annotations

import pytest
from helpers.scripted_cell import ScriptedCell

from nanodrift import Client
from nanodrift.cell_view import CellView


def test_open_returns_with_the_first_sample_of_a_measured_axis() -> None:
    cell = ScriptedCell("cvfirst", interferometer=True, first_position_um=42.5)
    try:
        with Client(cell.endpoint, cell=cell.cell) as client:
            view = CellView.open(client, timeout_s=10.0)
            try:
                measured = view.position("x")
                assert measured is not None and measured.value_um == pytest.approx(42.5, abs=1e-9)
                assert view.request({"x": 100.0}) == 100.0
            finally:
                view.close()
    finally:
        cell.close()


def test_a_sensor_that_never_publishes_only_delays_open() -> None:
    cell = ScriptedCell("cvsilent", interferometer=True)
    try:
        with Client(cell.endpoint, cell=cell.cell) as client:
            view = CellView.open(client, timeout_s=10.0)  # returns (after FIRST_POSITION_TIMEOUT_S) ...
            try:
                assert view.axes["x"].position_sensor == "interferometer"
                assert view.position("x") is None  # ... with no sample: STATE and MSG tell the rest
            finally:
                view.close()
    finally:
        cell.close()
