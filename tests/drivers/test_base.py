"""``nanodrift.drivers.base``: the contract's own pieces: readings, the common sensor keys and their checks, the
monotonic clock, and what the abstract classes give a plugin by default."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Sequence
from typing import Any

import pytest
from pydantic import ValidationError

from nanodrift.drivers.base import (
    Actuator,
    ActuatorOptions,
    DeviceError,
    DriverContext,
    DriverPlugin,
    MonotonicClock,
    Reading,
    SensorConfig,
    SensorGroup,
    State,
    VirtualCellPlugin,
)


def test_a_fault_reading_has_no_value_and_says_why() -> None:
    bad = Reading.fault(12.5, "open thermocouple", unit="degC")
    assert math.isnan(bad.value) and bad.t == 12.5 and bad.state is State.FAULT
    assert bad.reason == "open thermocouple" and bad.unit == "degC"
    ok = Reading(21.5, t=1.0)
    assert ok.state is State.OK and ok.reason == "" and ok.unit == ""
    with pytest.raises(AttributeError):
        ok.value = 3.0  # type: ignore[misc]
    assert [s.value for s in State] == ["ok", "stale", "fault"]
    assert issubclass(DeviceError, Exception) and not issubclass(DeviceError, (OSError, ValueError))


def sensor(**keys: Any) -> SensorConfig:
    return SensorConfig.model_validate({"name": "T1", "kind": "x", **keys})


@pytest.mark.parametrize(
    ("keys", "message"),
    [
        ({"interval_s": 1.0, "max_age_s": 0.5}, "max_age_s = 0.5 s is below interval_s = 1 s"),
        ({"valid_min": 10.0, "valid_max": 10.0}, "valid_max = 10 is not above valid_min = 10"),
        ({"interval_s": 2.0, "max_age_s": 10.0, "frozen_after_s": 1.0}, "frozen_after_s = 1 s is below interval_s"),
        ({"interval_s": 1e-300}, "interval_s"),
        ({"max_age_s": math.inf}, "max_age_s"),
        ({"scale": 0.1}, "scale"),  # not a common key: a typo is an error
        ({"interval_s": "0.5"}, "interval_s"),  # a number written as a string
        ({"name": "T 1"}, "name"),
    ],
)
def test_the_common_sensor_keys_refuse_what_cannot_work_naming_the_key(keys: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message.replace("(", r"\(")):
        sensor(**keys)


def test_frozen_after_s_defaults_by_role() -> None:
    assert sensor().frozen_after_s == 0.0  # a thermocouple in a stable room repeats legitimately
    assert sensor(role="position").frozen_after_s == 30.0
    assert sensor(role="position", interval_s=5.0, max_age_s=60.0).frozen_after_s == 50.0  # ten polls
    assert sensor(role="position", frozen_after_s=0.0).frozen_after_s == 0.0  # said: kept
    assert sensor().hub_name() is None
    assert sensor(interval_s=1.0, max_age_s=1.0).max_age_s == 1.0  # one interval is enough


def test_the_monotonic_clock_is_one_time_base_near_unix_time_and_does_not_follow_the_wall_clock(
        monkeypatch: pytest.MonkeyPatch) -> None:
    a, b = MonotonicClock(), MonotonicClock()
    assert abs(a.now() - time.time()) < 5.0  # labelled in unix seconds
    assert abs(b.now() - a.now()) < 0.1  # every instance reads the same time
    before = a.now()
    monkeypatch.setattr(time, "time", lambda: 0.0)  # the wall clock steps back 55 years
    assert a.now() >= before

    async def sleep() -> float:
        start = a.now()
        await a.sleep(0.05)
        await a.sleep(-1.0)  # a negative sleep returns at once
        return a.now() - start

    assert 0.05 <= asyncio.run(sleep()) < 1.0
    assert isinstance(DriverContext().clock, MonotonicClock)
    assert DriverContext().resources is not DriverContext().resources  # each context shares its own


class Output(Actuator):
    async def open(self) -> None: ...

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None: ...

    async def close(self) -> None: ...


class Plugin(DriverPlugin):
    name = "p"
    config_model = SensorConfig

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        return []


def test_what_an_actuator_and_a_plugin_get_by_default() -> None:
    output = Output()
    assert asyncio.run(output.read_back()) is None  # cannot say where the output is
    assert output.sent_voltage(4.123456789) == 4.123456789  # takes the float as it is
    assert output.limits_v is None and output.description == "actuator"
    plugin = Plugin()
    assert plugin.actuator_model is None and plugin.section is None and not isinstance(plugin, VirtualCellPlugin)
    with pytest.raises(ValueError, match="driver 'p' cannot move the stage"):
        plugin.create_actuator(ActuatorOptions(kind="p"), DriverContext())
    assert plugin.config_problems([], None) == []
    options = ActuatorOptions(kind="p")
    assert options.voltage_range_problem(0.0, 10.0, 0.02) is None and options.config_warnings(0, 10, 0.02, 0) == []
    with pytest.raises(ValidationError, match="chanel"):
        ActuatorOptions.model_validate({"kind": "p", "chanel": 2})
    with pytest.raises(TypeError):
        SensorGroup()  # type: ignore[abstract]
