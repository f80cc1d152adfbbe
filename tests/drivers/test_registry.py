"""``nanodrift.drivers.registry``: plugins found by name through the ``nanodrift.drivers`` entry points, a lab's
own included, and what a missing or wrong one says."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import lab_plugin

from nanodrift.drivers import registry
from nanodrift.drivers.base import DriverPlugin
from nanodrift.drivers.modbus.plugin import PLUGIN as MODBUS
from nanodrift.drivers.pi_gcs.plugin import PLUGIN as PI_GCS
from nanodrift.drivers.registry import GROUP, UnknownDriverError, available, load_plugin
from nanodrift.drivers.serial_line.plugin import PLUGIN as SERIAL_LINE
from nanodrift.drivers.simulated.plugin import PLUGIN as SIMULATED


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[None]:
    with lab_plugin.installed(tmp_path / "lab"):
        yield


def test_nanodrifts_own_plugins_are_found_by_name() -> None:
    assert GROUP == "nanodrift.drivers"
    assert available() == {"attocube_ids": "nanodrift.drivers.attocube_ids.plugin:PLUGIN",
                           "dcon": "nanodrift.drivers.dcon.plugin:PLUGIN",
                           "modbus": "nanodrift.drivers.modbus.plugin:PLUGIN",
                           "pi_gcs": "nanodrift.drivers.pi_gcs.plugin:PLUGIN",
                           "serial_line": "nanodrift.drivers.serial_line.plugin:PLUGIN",
                           "simulated": "nanodrift.drivers.simulated.plugin:PLUGIN"}
    assert load_plugin("modbus") is MODBUS
    assert load_plugin("serial_line") is SERIAL_LINE
    assert load_plugin("simulated") is SIMULATED
    assert load_plugin("pi_gcs") is PI_GCS
    assert sorted(load_plugin(kind).name for kind in available()) == ["attocube_ids", "dcon", "modbus", "pi_gcs",
                                                                       "serial_line", "simulated"]


def test_a_labs_plugin_installed_with_an_entry_point_is_found_and_forgotten_when_removed(lab: None) -> None:
    assert available()["labbox"] == "helpers.lab_plugin:PLUGIN"
    plugin = load_plugin("labbox")
    assert plugin is lab_plugin.PLUGIN and isinstance(plugin, DriverPlugin)
    assert load_plugin("labbox") is plugin  # loaded once
    assert sorted(load_plugin(kind).name for kind in available()) == ["attocube_ids", "dcon", "labbox", "modbus",
                                                                       "pi_gcs", "serial_line", "simulated"]


def test_after_the_lab_package_is_gone_its_kind_is_unknown(tmp_path: Path) -> None:
    with lab_plugin.installed(tmp_path / "lab"):
        assert "labbox" in available()
    assert "labbox" not in available()
    with pytest.raises(UnknownDriverError) as error:
        load_plugin("labbox")
    assert str(error.value) == ("unknown sensor kind 'labbox'; installed driver kinds: attocube_ids, dcon, modbus, "
                                "pi_gcs, "
                                "serial_line, simulated")


def test_a_misspelt_kind_names_every_installed_kind() -> None:
    with pytest.raises(UnknownDriverError, match=r"unknown sensor kind 'modbsu'; installed driver kinds: "
                                                 r"attocube_ids, dcon, modbus, pi_gcs, serial_line, simulated$"):
        load_plugin("modbsu")
    assert isinstance(UnknownDriverError("x"), LookupError)


def test_an_entry_point_that_names_something_else_than_a_plugin_is_refused_naming_it(tmp_path: Path) -> None:
    entry = "broken = test_registry_target:NOT_A_PLUGIN"
    target = tmp_path / "lab" / "test_registry_target.py"
    target.parent.mkdir(parents=True)
    target.write_text("NOT_A_PLUGIN = object()\n")
    with lab_plugin.installed(tmp_path / "lab", entry):
        with pytest.raises(UnknownDriverError) as error:
            load_plugin("broken")
    assert str(error.value) == ("driver 'broken' (test_registry_target:NOT_A_PLUGIN) is not a "
                                "nanodrift.drivers.base.DriverPlugin instance")


def test_a_table_owned_by_a_kind_the_config_uses_is_found_without_listing_the_installed_plugins(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``[simulation]`` of a simulated cell: its own kind answers, before every entry point is listed (~4 ms);
    a table no kind in use owns is still looked for in every installed plugin."""
    listed: list[bool] = []
    monkeypatch.setattr(registry, "available", lambda: listed.append(True) or {"simulated": "", "modbus": ""})
    assert registry.owner_of_section("simulation", ["simulated"]) == "simulated"
    assert not listed
    assert registry.owner_of_section("simulation", ["modbus"]) == "simulated"
    assert listed
