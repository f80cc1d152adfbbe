"""The registry's two questions (which plugin owns a table, which is the virtual cell) and the typed
shared resources of a driver context."""

from __future__ import annotations

import pytest

from nanodrift.drivers.base import DriverPlugin, SharedResources, StrictModel, VirtualCellPlugin
from nanodrift.drivers.registry import load_plugin, owner_of_section, quietly, virtual_cell_plugin
from nanodrift.drivers.simulated.clock import ScaledClock


def test_the_simulated_plugin_owns_its_table_and_is_the_virtual_cell() -> None:
    assert owner_of_section("simulation") == "simulated"
    assert owner_of_section("simulation", ["modbus"]) == "simulated"  # the kinds in use first, then the rest
    assert owner_of_section("no_such_table") is None
    found = virtual_cell_plugin(["modbus", "simulated", "serial_line"])
    assert found is not None and found[0] == "simulated" and isinstance(found[1], VirtualCellPlugin)
    assert virtual_cell_plugin(["modbus", "serial_line"]) is None
    assert not isinstance(load_plugin("modbus"), VirtualCellPlugin)


def test_a_loader_that_fails_is_skipped_not_raised() -> None:
    assert quietly("no_such_kind") is None
    asked: list[str] = []

    def load(kind: str) -> DriverPlugin | None:
        asked.append(kind)
        return None if kind == "modbus" else quietly(kind)

    assert owner_of_section("simulation", ["modbus"], load) == "simulated"
    assert asked[0] == "modbus"


def test_shared_resources_are_typed_on_the_way_out() -> None:
    resources = SharedResources()
    assert resources.get("x.clock", ScaledClock) is None
    clock = ScaledClock(2.0)
    resources.put("x.clock", clock)
    assert resources.get("x.clock", ScaledClock) is clock
    hubs: dict[str, int] = resources.setdefault("x.hubs", {})
    hubs["a"] = 1
    assert resources.setdefault("x.hubs", {}) == {"a": 1}
    with pytest.raises(TypeError, match=r"'x\.clock' is a ScaledClock, not a dict"):
        resources.get("x.clock", dict)
    with pytest.raises(TypeError, match=r"'x\.hubs' is a dict, not a list"):
        resources.setdefault("x.hubs", [])


def test_every_table_of_the_config_is_strict() -> None:
    class Table(StrictModel):
        scale: float = 1.0

    with pytest.raises(ValueError, match="valid number"):
        Table.model_validate({"scale": "0.1"})
    with pytest.raises(ValueError, match="Extra inputs"):
        Table.model_validate({"sclae": 0.1})
    with pytest.raises(ValueError, match="finite"):
        Table.model_validate({"scale": float("inf")})
