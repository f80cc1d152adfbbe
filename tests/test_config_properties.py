"""Property-based: any operator config document, valid or not, gives a Config or a ConfigError whose
every problem names a field path (issue 10: no traceback ever, a message naming the field).

Documents are drawn from the contract's own sections and keys, each key with good values, values of
the wrong type, non-finite and out-of-range numbers, typos and structural mistakes (a table where
an array of tables belongs, ...) and deeply nested arrays and tables. They go through
``parse_config`` directly, and as TOML text through ``load_config`` (which adds the TOML parser and
the file's folder for relative paths). TOML text nested far deeper than any parser follows
(``x = [[[...`` 100000 levels) is a ConfigError naming the file, never a RecursionError.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path
from typing import Any

import pytest
from helpers.budget import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nanodrift.config import TOO_DEEP, Config, ConfigError, load_config, parse_config
from nanodrift.drivers.base import MAX_AGE_S, MAX_INTERVAL_S, MIN_INTERVAL_S
from nanodrift.drivers.simulated.config import MAX_SPEED

SOURCE = "props.toml"
SETTINGS = settings(max_examples=examples(150), deadline=None, suppress_health_check=[HealthCheck.too_slow])

# --- values ----------------------------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6, max_value=1e6)
non_finite = st.sampled_from([math.inf, -math.inf, math.nan])
odd_text = st.text(alphabet=st.characters(codec="utf-8", exclude_categories=["Cs"]), max_size=12)
scalar = st.one_of(st.booleans(), st.integers(-(2**63), 2**63 - 1), finite, non_finite, odd_text)


def nested(depth: int, leaf: Any, shapes: list[bool]) -> Any:
    """``leaf`` inside ``depth`` arrays or one-key tables (``shapes[i % len]``: a table), built without recursion."""
    value = leaf
    for level in range(depth):
        value = {"a": value} if shapes[level % len(shapes)] else [value]
    return value


def deep(max_depth: int) -> st.SearchStrategy[Any]:
    """Arrays and tables nested up to ``max_depth`` levels, around any scalar."""
    return st.builds(nested, st.integers(2, max_depth), scalar, st.lists(st.booleans(), min_size=1, max_size=3))


#: deep enough to be hostile, shallow enough for this file's recursive TOML writer and tomllib
#: (the text test below goes to 150000 levels)
anything = st.one_of(st.recursive(scalar, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                                  st.dictionaries(odd_text, inner, max_size=3)),
                                  max_leaves=6),
                     deep(120))


def number(good: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    """A numeric key: good values most of the time, else a non-finite, negative, zero, huge, tiny or
    wrong-typed one."""
    return st.one_of(good, good, non_finite, st.sampled_from([0, -1, 0.0, -0.5, 1e308, -1e308, 1e-300, 1e9]),
                     scalar)


def choice(good: list[Any]) -> st.SearchStrategy[Any]:
    return st.one_of(st.sampled_from(good), st.sampled_from(good), scalar)


def key(good: list[str]) -> st.SearchStrategy[str]:
    """A key inside a TOML table: always a string, known or not."""
    return st.one_of(st.sampled_from(good), st.sampled_from(good), odd_text)


def table(fields: dict[str, st.SearchStrategy[Any]], typos: list[str]) -> st.SearchStrategy[dict[str, Any]]:
    """Some of the fields, sometimes a misspelt key, sometimes a value of any shape under a known key."""
    keys = st.lists(st.sampled_from(sorted(fields)), unique=True, max_size=len(fields))

    @st.composite
    def build(draw: st.DrawFn) -> dict[str, Any]:
        out = {k: draw(fields[k]) for k in draw(keys)}
        if typos and draw(st.integers(0, 4)) == 0:
            out[draw(st.sampled_from(typos))] = draw(scalar)
        if out and draw(st.integers(0, 6)) == 0:
            out[draw(st.sampled_from(sorted(out)))] = draw(anything)
        return out

    return build()


positive = st.floats(min_value=0.01, max_value=100.0)
channel_name = st.one_of(st.sampled_from(["T1", "T2", "T3", "T4", "interferometer", "air", "stage"]),
                         st.sampled_from(["", "1T", "x y", "T1\n", "é"]), odd_text)

ZENOH = table({
    "mode": choice(["peer", "client", "router"]),
    "listen": st.one_of(st.just(["tcp/127.0.0.1:7447"]), st.lists(odd_text, max_size=2), scalar),
    "connect": st.one_of(st.just(["tcp/10.0.0.2:7447"]), st.lists(scalar, max_size=2)),
    "multicast_scouting": choice([True, False]),
    "config_file": choice(["zenoh.json5", "/etc/nanodrift/zenoh-secure.json5"]),
}, ["multicast", "listen_on", "conect"])
MODEL = table({"path": choice(["model.json", "/var/lib/nanodrift/model.json", "../m.json"])}, ["pth"])
ACTUATOR = table({
    "volts_per_um": number(st.floats(0.001, 0.1)), "offset_v": number(finite), "v_min": number(finite),
    "v_max": number(finite), "x_min_um": number(finite), "x_max_um": number(finite),
    "position_proof_tolerance_um": number(st.floats(0.001, 100.0)),
}, ["volts_per_umm", "vmax", "kind_"])
SIMULATION = table({
    "scenario": choice(["train", "steady", "room", "test2", "daily", "nope"]),
    "speed": number(st.floats(0.1, 20000.0)), "seed": number(st.integers(0, 100)),
    "effects": st.one_of(st.lists(choice(["thermal_lag", "hysteresis", "creep", "bogus"]), max_size=3),
                         st.dictionaries(key(["thermal_lag", "creep"]),
                                         st.dictionaries(key(["tau_s", "gain"]), number(positive), max_size=2),
                                         max_size=2)),
    "params": st.dictionaries(key(["drift_um_per_c", "noise_nm", "unknown_param"]), number(finite), max_size=2),
}, ["sped", "scenarion"])
COMMON_SENSOR = {
    "name": channel_name, "role": choice(["temperature", "position"]),
    "interval_s": number(positive), "max_age_s": number(positive), "timeout_s": number(positive),
}
SENSOR = st.one_of(
    table({**COMMON_SENSOR, "kind": choice(["simulated"])}, ["intervall_s"]),
    table({**COMMON_SENSOR, "kind": choice(["modbus"]), "hub": choice(["adam", "missing"]),
           "device_id": number(st.integers(0, 255)), "address": number(st.integers(0, 65535)),
           "input_type": choice(["input", "holding", "coil"]),
           "data_type": choice(["int16", "uint16", "int32", "uint32", "float32", "int8"]),
           "swap": choice(["none", "byte", "word", "word_byte", "bytes"]), "scale": number(finite),
           "offset": number(finite), "nan_value": number(st.integers(-32768, 65535))}, ["nan_valeu", "adress"]),
    table({**COMMON_SENSOR, "kind": choice(["serial_line"]), "port": choice(["/dev/ttyUSB0", "socket://h:1"]),
           "baudrate": number(st.integers(1, 115200)), "query": choice(["POS?\r", ""]),
           "pattern": choice([r"P (?P<value>[-+0-9.]+) nm", r"(?P<value>", "no group", r"(?P<v>\d+)"]),
           "scale": number(finite), "eol": choice(["\n", "\r\n", "\r", "x"])}, ["paterne"]),
    table({"name": channel_name, "kind": choice(["no_such_driver", ""])}, []),
)
HUB = table({
    "name": choice(["adam", "rs485"]), "type": choice(["tcp", "serial", "udp"]), "host": choice(["192.168.1.20"]),
    "port": number(st.integers(1, 65535)), "timeout_s": number(positive), "retries": number(st.integers(0, 3)),
    "baudrate": number(st.integers(1, 115200)), "parity": choice(["N", "E", "O", "X"]),
}, ["hots"])

SECTIONS: dict[str, st.SearchStrategy[Any]] = {
    "cell": choice(["cell0", "lab-1", "bad cell", "", "a/b"]),
    "zenoh": st.one_of(ZENOH, ZENOH, scalar),
    "model": st.one_of(MODEL, MODEL, scalar),
    "actuator": st.one_of(ACTUATOR, ACTUATOR, scalar),
    "simulation": st.one_of(SIMULATION, SIMULATION, scalar),
    "hubs": st.one_of(st.lists(HUB, max_size=2), st.lists(scalar, max_size=2), scalar),
    "sensors": st.one_of(st.lists(SENSOR, max_size=4), st.lists(SENSOR, max_size=4),
                         st.lists(scalar, max_size=2), SENSOR, scalar),
    "sensor": st.lists(SENSOR, max_size=1),  # a typo of [[sensors]]
    "celll": scalar,
}


@st.composite
def any_document(draw: st.DrawFn) -> dict[str, Any]:
    names = draw(st.lists(st.sampled_from(sorted(SECTIONS)), unique=True, max_size=len(SECTIONS)))
    return {name: draw(SECTIONS[name]) for name in names}


def leaves(node: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    if isinstance(node, dict):
        return [p for k, v in node.items() for p in leaves(v, (*path, k))]
    if isinstance(node, list):
        return [p for i, v in enumerate(node) for p in leaves(v, (*path, i))]
    return [path]


@st.composite
def near_valid_document(draw: st.DrawFn) -> dict[str, Any]:
    """A valid cell (simulated, or Modbus + serial), then at most one field broken: most are accepted."""
    n = draw(st.integers(1, 4))
    intervals = [draw(positive) for _ in range(n)]  # max_age_s at least interval_s: a valid cell
    timing = [{"interval_s": i, "max_age_s": i * draw(st.floats(1.0, 20.0))} for i in intervals]
    doc: dict[str, Any] = {"cell": "c0", "actuator": {"volts_per_um": 0.02, "v_min": -2.0, "v_max": 12.0}}
    if draw(st.booleans()):
        doc["simulation"] = {"scenario": "steady", "speed": draw(st.floats(0.1, 100.0))}
        doc["sensors"] = [{"name": f"T{i + 1}", "kind": "simulated", **timing[i]} for i in range(n)]
    else:
        doc["hubs"] = [{"name": "adam", "host": "127.0.0.1", "port": 502}]
        doc["sensors"] = [{"name": f"T{i + 1}", "kind": "modbus", "hub": "adam", "address": i, "scale": 0.1,
                           **timing[i]} for i in range(n)]
        doc["sensors"].append({"name": "interferometer", "role": "position", "kind": "serial_line",
                               "port": "socket://127.0.0.1:4001", "pattern": r"P (?P<value>[-+0-9.]+) nm"})
    if draw(st.booleans()):
        *parents, last = draw(st.sampled_from(leaves(doc)))
        node = doc
        for part in parents:
            node = node[part]
        node[last] = draw(st.one_of(non_finite, st.sampled_from([0, -1, 0.0, 1e308, "1.0", "", [], {}]), scalar))
    return doc


def documents() -> st.SearchStrategy[dict[str, Any]]:
    return st.one_of(any_document(), near_valid_document())


# --- what must hold --------------------------------------------------------------------------------

#: the root of a field path: ``sensors`` in ``sensors[2] (T3).scale: ...``, ``zenoh`` in ``zenoh.listen[0]: ...``
FIELD_ROOT = re.compile(r"^(?P<root>\(top level\)|[^\s.\[:()]+)(?P<rest>[^:]*?|.*?[\].)].*?): \S", re.DOTALL)


def check_outcome(data: Any, parse: Any, text: bool = False) -> None:
    try:
        config = parse()
    except ConfigError as error:
        assert error.problems, "a ConfigError with no problem line"
        for problem in error.problems:
            if text and re.match(r"^not valid TOML: .*\(at line \d+, column \d+\)$", problem, re.DOTALL):
                continue  # the document is not TOML: the file's line and column are the place
            if text and problem == TOO_DEEP:
                continue  # nested deeper than the parser follows: the file is the place
            match = FIELD_ROOT.match(problem)
            assert match, f"problem does not start with a field path: {problem!r}"
            root = match["root"]
            assert root == "(top level)" or root in data or root in Config.model_fields, (root, problem)
        first_lines = [str(error).split(f"\n{error.source}:")[0], *str(error).split(f"\n{error.source}:")[1:]]
        assert str(error).startswith(f"{error.source}:") and len(first_lines) == len(error.problems), str(error)
        return
    assert isinstance(config, Config)
    # what was accepted is finite and physical
    for sensor in config.sensors:
        for key in ("interval_s", "max_age_s", "timeout_s"):
            value = getattr(sensor, key)
            assert math.isfinite(value) and value > 0, (sensor, key)
        assert MIN_INTERVAL_S <= sensor.interval_s <= MAX_INTERVAL_S, sensor
        assert sensor.interval_s <= sensor.max_age_s <= MAX_AGE_S, sensor
        scale = getattr(sensor, "scale", 1.0)
        assert math.isfinite(scale) and scale != 0, sensor
    simulation = config.section("simulation")
    if simulation is not None:
        assert 0 < simulation.speed <= MAX_SPEED, simulation  # type: ignore[attr-defined]
    actuator = config.actuator
    # nan says something in these: leave the stage; every first start is confirmed; a position sensor proves nothing
    nan_means = {"safe_voltage_v", "power_up_voltage_v", "position_proof_tolerance_um"}
    finite_keys = {k: v for k, v in actuator.model_dump().items() if isinstance(v, float) and k not in nan_means}
    assert all(math.isfinite(v) for v in finite_keys.values()), actuator
    tolerance_um = actuator.position_proof_tolerance_um
    assert math.isnan(tolerance_um) or 0 < tolerance_um < math.inf, actuator
    assert actuator.v_min < actuator.v_max and actuator.x_min_um < actuator.x_max_um and actuator.volts_per_um != 0


@SETTINGS
@given(documents())
def test_parse_config_gives_a_config_or_a_config_error_naming_fields(data: dict[str, Any]) -> None:
    check_outcome(data, lambda: parse_config(data, source=SOURCE, base_dir=Path("/etc/nanodrift")))


# --- as TOML text, through the file loader -----------------------------------------------------------


def toml_string(text: str) -> str:
    """A TOML basic string: quotes and backslashes escaped, control characters as \\uXXXX."""
    return '"' + "".join(f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else "\\" + c if c in '"\\' else c
                         for c in text) + '"'


def toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return toml_string(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return "{" + ", ".join(f"{toml_string(k)} = {toml_value(v)}" for k, v in value.items()) + "}"


def toml_document(data: dict[str, Any]) -> str:
    """Top-level keys, then ``[tables]``, then ``[[arrays of tables]]``: what an operator writes."""
    lines = [f"{toml_string(k)} = {toml_value(v)}" for k, v in data.items()
             if not isinstance(v, dict) and not (isinstance(v, list) and v and all(isinstance(i, dict) for i in v))]
    for key, value in data.items():
        if isinstance(value, dict):
            lines += [f"[{toml_string(key)}]"] + [f"{toml_string(k)} = {toml_value(v)}" for k, v in value.items()]
    for key, value in data.items():
        if isinstance(value, list) and value and all(isinstance(i, dict) for i in value):
            for item in value:
                lines += [f"[[{toml_string(key)}]]"] + [f"{toml_string(k)} = {toml_value(v)}" for k, v in item.items()]
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("config_props")


@SETTINGS
@given(documents(), st.sampled_from(["", "", "[actuator\n", "= 1\n", "cell = 'a'\ncell = 'b'\n", "\x00", "\ufeff"]))
def test_load_config_on_toml_text_gives_a_config_or_a_config_error_naming_fields(
        folder: Path, data: dict[str, Any], damage: str) -> None:
    text = toml_document(data)
    assert tomllib.loads(text).keys() == data.keys()  # the serializer writes what was drawn
    path = folder / "nanodrift.toml"
    path.write_text(damage + text, encoding="utf-8")
    parsed = tomllib.loads(text) if not damage else {}
    check_outcome(parsed, lambda: load_config(path), text=True)


# --- nested deeper than any parser follows ------------------------------------------------------------

OPENERS = {"array": ("[", "]"), "table": ("{a = ", "}"), "mixed": ("[{a = ", "}]")}


@SETTINGS
@given(st.sampled_from(["x", "cell", "sensors", "hubs", "simulation.effects", "simulation.params", "actuator.v_min"]),
       st.sampled_from(sorted(OPENERS)), st.one_of(st.integers(1, 400), st.integers(400, 150_000)),
       st.sampled_from(["1", "nan", '"T1"', "[]", "{}"]), st.booleans())
def test_load_config_on_deeply_nested_toml_gives_a_config_error_naming_file_or_field(
        folder: Path, where: str, shape: str, depth: int, leaf: str, before_valid_text: bool) -> None:
    opener, closer = OPENERS[shape]
    table, _, key = where.rpartition(".")
    line = f"{key} = {opener * depth}{leaf}{closer * depth}\n"
    text = (f"[{table}]\n" if table else "") + line
    if before_valid_text:  # a hostile value in an otherwise good file
        text = text + '[actuator]\nvolts_per_um = 0.02\n' if table != "actuator" else text
    path = folder / "deep.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    error = info.value
    assert error.source == str(path) and str(error).startswith(f"{path}:")
    root = table or key
    for problem in error.problems:
        assert problem == TOO_DEEP or problem.startswith((f"{root}:", f"{root}.", f"{root}[")), problem
    if depth >= 5000:  # far beyond what tomllib follows on any stack
        assert error.problems == [TOO_DEEP], error.problems


@SETTINGS
@given(st.sampled_from(["cell", "sensors", "hubs", "zenoh", "model", "simulation", "actuator", "health"]),
       st.integers(2, 20_000), scalar, st.lists(st.booleans(), min_size=1, max_size=3), st.booleans())
def test_parse_config_on_deeply_nested_values_names_the_field(section: str, depth: int, leaf: Any,
                                                              shapes: list[bool], under_a_key: bool) -> None:
    value = nested(depth, leaf, shapes)
    data = {section: {"params" if section == "simulation" else "x": value} if under_a_key else value}
    with pytest.raises(ConfigError) as info:
        parse_config(data, source=SOURCE, base_dir=Path("/etc/nanodrift"))
    for problem in info.value.problems:
        assert problem.startswith((f"{section}:", f"{section}.", f"{section}[")), problem
