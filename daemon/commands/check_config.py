"""``nanodrift check-config F [--strict]``: validate an operator config before reloading it.

Exit 2 (with ``<file>:<line>: <field>: <problem>`` lines) for everything the daemon would refuse on
a reload (:func:`model_problem`, :func:`zenoh_problem`, :func:`no_sensors`, :func:`safe_stop`). Exit 0 with
warnings on stderr for what the daemon accepts but an operator should know (:func:`config_warnings`), in the
errors' form (``<file>:<line>: warning: sensors[2] (T3).name: ...``); ``--strict`` makes those errors too,
for a commissioned cell where they are mistakes.
"""

from __future__ import annotations

import argparse
import ipaddress
import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path

import zenoh

from nanodrift.bus.protocol import Keys
from nanodrift.bus.session import session_config
from nanodrift.compensation import load_served_model
from nanodrift.config import (
    SAFE_RAMP_BUDGET_S,
    STOP_TIMEOUT_S,
    ZENOH_KIND,
    Config,
    ConfigError,
    actuator_line,
    load_config,
    locate,
    missing_model_channels,
)
from nanodrift.drivers.base import VirtualCellPlugin
from nanodrift.drivers.registry import UnknownDriverError, load_plugin
from nanodrift.model.cell_model import CellModel
from nanodrift.model.model import Model, ModelFileError
from nanodrift.motion import SAFE_RATE_SHARE


def model_problem(config: Config) -> tuple[Model | CellModel | None, str | None]:
    """The model the daemon would load, or a ``model.path: ...`` problem line saying why it would refuse it
    (a model of other axes than the cell's included)."""
    try:
        return load_served_model(config.model.path, config.axis_names), None
    except ModelFileError as error:
        reason = str(error)
    except RecursionError:  # a hostile, deeply nested JSON document
        reason = f"{config.model.path}: JSON nested too deeply to be a model file"
    return None, (f"model.path: {reason} (a reload with this file is refused; at start the daemon runs "
                  "without a model and refuses every target with no_model)")


def zenoh_problem(config: Config) -> str | None:
    """A ``zenoh.config_file: ...`` problem line when zenoh cannot read the file (the daemon could not start)."""
    if config.zenoh.config_file is None:
        return None
    try:
        session_config(config.zenoh)
    except (zenoh.ZError, OSError, ValueError) as error:
        return f"zenoh.config_file: {config.zenoh.config_file}: zenoh cannot use it: {error}"
    return None


#: endpoints only this computer can reach: tcp/127.0.0.1:7447, tcp/localhost:7447, tcp/[::1]:7447, unixsock-stream/...
_LOCAL_ENDPOINT = re.compile(r"^(?:[a-z]+/(?:127\.\d+\.\d+\.\d+|localhost|\[::1\]):\d+|unixsock-stream/.*)$")


def zenoh_exposed(config: Config) -> list[str]:
    """zenoh listening beyond this computer without its authentication and access control (README, "Securing the
    network")."""
    if config.zenoh.config_file is not None:
        return []
    exposed = [e for e in config.zenoh.listen if not _LOCAL_ENDPOINT.match(e.split("#", 1)[0])]
    if not exposed:
        return []
    return [f"zenoh.listen: {', '.join(exposed)} can be reached from other computers, and without a "
            "zenoh.config_file (credentials, access control) any of them may send targets or put its own "
            "command: see README.md, 'Securing the network' (config/zenoh-secure.json5)"]


def safe_stop(config: Config) -> tuple[list[str], list[str]]:
    """(what the safe stop takes, per axis; why it cannot finish in time, per axis) for every axis with a finite
    ``safe_voltage_v`` and a slew limit.

    systemd kills the daemon :data:`STOP_TIMEOUT_S` after SIGTERM and the ramp may use :data:`SAFE_RAMP_BUDGET_S`
    of it. The longest ramp starts at the limit farthest from the safe voltage; whatever the device's latency it
    runs at >= :data:`nanodrift.motion.SAFE_RATE_SHARE` of the rate (a ramp waits
    :data:`nanodrift.motion.LATENCY_PAUSES` times the device's write time between steps), so that bounds its
    duration. A stop that cannot finish is refused: the stage would be left between two voltages, energised.
    """
    said: list[str] = []
    problems: list[str] = []
    for (where, one), axis in zip(_per_axis(config), config.axis_names, strict=True):
        a = one.actuator
        ramp = a.safe_ramp()
        if ramp is None:
            continue
        nominal_s, distance_um, from_v = ramp
        bound_s = nominal_s / SAFE_RATE_SHARE
        said.append(f"  safe stop: axis {axis} to {a.safe_voltage_v:g} V in at most {bound_s:.3g} s "
                    f"(from {from_v:g} V: {distance_um:.4g} um at {a.max_slew_um_per_s:g} um/s, at least "
                    f"{SAFE_RATE_SHARE:.0%} of it whatever the device's latency); budget {SAFE_RAMP_BUDGET_S:g} s")
        if bound_s > SAFE_RAMP_BUDGET_S:
            needed = distance_um / (SAFE_RAMP_BUDGET_S * SAFE_RATE_SHARE)
            problems.append(
                f"{where}.max_slew_um_per_s: the ramp to safe_voltage_v = {a.safe_voltage_v:g} V at a stop can take "
                f"{bound_s:.4g} s (from {from_v:g} V: {distance_um:.4g} um at {a.max_slew_um_per_s:g} um/s, at "
                f"{SAFE_RATE_SHARE:.0%} of it on a slow device), more than the {SAFE_RAMP_BUDGET_S:g} s of the "
                f"{STOP_TIMEOUT_S:g} s stop timeout it may use: the daemon would give up with the stage short of "
                f"the safe voltage; allow at least {needed:.4g} um/s, narrow [v_min, v_max], or set "
                "safe_voltage_v = nan (leave the stage where it is)")
    return said, problems


def metrics_exposed(config: Config) -> list[str]:
    """``[metrics] listen`` on anything but loopback (0.0.0.0, ::, a lab address, a host name): the metrics page
    has no authentication at all."""
    host = config.metrics.host
    if not host or host == "localhost":
        return []
    try:
        if ipaddress.ip_address(host).is_loopback:
            return []
    except ValueError:  # a host name: it may resolve to any interface
        pass
    return [f"metrics.listen: {config.metrics.listen}: the metrics page is open to the network (no "
            "authentication: whoever reaches the port reads the cell's sensors, model and counters); keep it on "
            "127.0.0.1, or on a monitoring network behind a firewall (the unit allows only localhost until "
            "a drop-in's IPAddressAllow=)"]


def actuator_warnings(config: Config) -> list[str]:
    """The actuator plugin's own warnings (a command template coarser than the stage needs), named by key."""
    a = config.actuator
    if a.options is None:
        return []
    return [actuator_line(a.options, w) for w in a.options.config_warnings(a.v_min, a.v_max, a.volts_per_um,
                                                                            a.offset_v)]


def driver_warnings(config: Config) -> list[str]:
    """Each driver plugin's warnings across its sensors and its actuator (a shared port, ...)."""
    options = config.actuator.options
    sensors = list(enumerate(config.sensors))
    kinds = dict.fromkeys([s.kind for _, s in sensors] + ([options.kind] if options is not None else []))
    warnings: list[str] = []
    for kind in kinds:
        try:
            plugin = load_plugin(kind)
        except UnknownDriverError:  # the config was read with it: cannot happen, and nothing to warn about
            continue
        warnings += plugin.config_warnings([(i, s) for i, s in sensors if s.kind == kind],
                                           options if options is not None and options.kind == kind else None)
        if isinstance(plugin, VirtualCellPlugin):  # its clock times every sensor
            section = config.section(plugin.section) if plugin.section else None
            warnings += plugin.timing_warnings(section, sensors)
    return warnings


def position_window_warnings(config: Config) -> list[str]:
    """A position sensor that polls no faster than ``[health] window_s`` (both seconds of the cell's clock); the
    warning says what a held target then misses."""
    window_s = config.health.window_s
    return [f"sensors[{index}] ({sensor.name}).interval_s: polls every {sensor.interval_s:g} s, not faster than "
            f"[health] window_s = {window_s:g} s: a held target whose window no reading falls into gets no residual "
            f"and no record row (counted as holds_unrecorded); make window_s larger than {sensor.interval_s:g} s or "
            "poll faster"
            for index, sensor in enumerate(config.sensors)
            if sensor.role == "position" and sensor.interval_s >= window_s]


def position_proofs(config: Config) -> tuple[list[str], list[str]]:
    """(what each axis' position proof may believe, warnings) for every axis stating
    ``position_proof_tolerance_um``: the lines say how far a first move may jump, the warnings a tolerance with
    nothing to prove with or so wide a sensor proves almost any read-back."""
    said: list[str] = []
    warnings: list[str] = []
    sensors = config.position_sensors()
    for (where, one), axis in zip(_per_axis(config), config.axis_names, strict=True):
        a = one.actuator
        tolerance_um = a.position_proof_tolerance_um
        if math.isnan(tolerance_um):
            continue
        key = f"{where}.position_proof_tolerance_um"
        sensor = sensors.get(axis)
        if a.kind == ZENOH_KIND:
            warnings.append(f"{key}: kind zenoh reads no output back: there is nothing for a position sensor to prove")
            continue
        if sensor is None:
            warnings.append(f"{key}: no position sensor measures axis {axis} (role = \"position\", axis = "
                            f"\"{axis}\"): a read-back nothing on record confirms stays refused")
            continue
        said.append(f"  position proof: axis {axis} by {sensor.name}: a read-back nothing on record confirms is "
                    f"believed within {tolerance_um:g} um ({tolerance_um * abs(a.volts_per_um):.4g} V) of its "
                    "reading: the most a first move may jump")
        span_um = a.x_max_um - a.x_min_um
        if tolerance_um >= span_um / 2:
            warnings.append(f"{key}: {tolerance_um:g} um is half the axis' workspace ({span_um:g} um) or more: a "
                            "position sensor would prove almost any read-back; state the model's largest correction "
                            "|q - x| plus the sensor's uncertainty")
    return said, warnings


def config_warnings(config: Config, model: Model | CellModel | None) -> list[str]:
    """``field: message`` lines for what the daemon accepts but an operator should know."""
    warnings = (zenoh_exposed(config) + metrics_exposed(config) + position_window_warnings(config)
                + position_proofs(config)[1])
    for where, one in _per_axis(config):  # a multi-axis cell: each axis' actuator as a one-axis cell's
        for warning in actuator_warnings(one) + driver_warnings(one):
            warning = where + warning[len("actuator"):] if warning.startswith("actuator") else warning
            if warning not in warnings:
                warnings.append(warning)
    if model is None:
        return warnings
    missing = missing_model_channels(config, model.channels)
    if missing:
        warnings.append(
            f"sensors: model {model.id} needs channel(s) {', '.join(missing)} that no temperature sensor provides: "
            "targets will be refused until they are configured"
        )
    for index, sensor in enumerate(config.sensors):
        if sensor.role == "temperature" and sensor.name not in model.channels:
            warnings.append(f"sensors[{index}] ({sensor.name}).name: sensor {sensor.name!r} is not used by model "
                            f"{model.id} (monitored and published only)")
    return warnings


def describe_actuator(config: Config) -> str:
    """Who puts the voltage on the amplifier, in the operator's words."""
    a = config.actuator
    limits = f"[{a.v_min:g}, {a.v_max:g}] V"
    if a.kind == ZENOH_KIND:
        return f"kind zenoh: an output node applies {Keys(config.cell, config.zenoh.prefix).command}, {limits}"
    keys = a.options.model_dump(exclude={"kind"}) if a.options is not None else {}
    where = ", ".join(f"{k} = {v!r}" for k, v in keys.items() if k in ("hub", "device_id", "address", "port"))
    return f"kind {a.kind}" + (f" ({where})" if where else "") + f", {limits}"


def _per_axis(config: Config) -> list[tuple[str, Config]]:
    """(where, the config as a one-axis cell's with that axis' actuator) for every axis."""
    if not config.multi_axis:
        return [("actuator", config)]
    return [(f"axes[{i}] ({axis}).actuator", config.model_copy(update={"actuator": actuator}))
            for i, (axis, actuator) in enumerate(config.axis_actuators().items())]


def no_sensors(config: Config, model: Model | CellModel | None) -> tuple[str | None, str | None]:
    """(problem, warning) for a config that lists no sensors, as the daemon's reload rule judges it.

    A reload never removes every sensor of a running cell (daemon/service/reload.py). A sensor-less
    file whose model needs temperature channels (an emptied file gets the shipped model) could serve
    nothing, so it can only be that slip: an error. One whose model needs no channel is a cell a
    daemon may run (it starts with it, a sensor-less daemon reloads it): a warning.
    """
    if config.sensors or model is None:
        return None, None
    refused = "a running daemon with sensors refuses it on reload (a reload never removes every sensor)"
    if model.channels:
        return (f"sensors: the config lists no sensors (an emptied file?) and model {model.id} needs "
                f"{', '.join(model.channels)}: {refused}, and a daemon started with it refuses every target; "
                "to run a cell without sensors on purpose, start it by hand: nanodrift run --config FILE"), None
    return None, f"sensors: the config lists no sensors: {refused}; a restart applies it"


def file_lines(path: str, problems: Sequence[str]) -> list[int | None]:
    """The line of the file each problem or warning is at (as :func:`nanodrift.config.load_config` finds
    it for the errors it raises), None where no line holds it."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return [None] * len(problems)
    return [locate(text, p) for p in problems]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="F", help="the operator config (TOML) to check")
    parser.add_argument("--strict", action="store_true",
                        help="warnings (a channel the model needs is missing, unused sensors) are errors too")


def main(args: argparse.Namespace) -> int:
    config = load_config(args.file)
    model, problem = model_problem(config)
    emptied, sensorless = no_sensors(config, model)
    stop_said, stop_problems = safe_stop(config)
    problems = [p for p in (problem, zenoh_problem(config), emptied) if p] + stop_problems
    warnings = config_warnings(config, model) + ([sensorless] if sensorless else [])
    if args.strict:
        problems += [f"{w} (an error with --strict)" for w in warnings]
        warnings = []
    if problems:
        raise ConfigError(config.source, problems, file_lines(args.file, problems))
    names = ", ".join(f"{s.name} ({s.kind}, {s.role})" for s in config.sensors)
    print(f"{args.file}: ok: cell {config.cell!r}, {len(config.sensors)} sensor(s): {names}")
    print(f"  model: {config.model.path} ({model.id if model else '-'})")
    if config.multi_axis:
        for (_, one), axis in zip(_per_axis(config), config.axis_names, strict=True):
            a = one.actuator
            print(f"  axis {axis}: [{a.x_min_um:g}, {a.x_max_um:g}] um, actuator: {describe_actuator(one)}")
    else:
        print(f"  actuator: {describe_actuator(config)}")
    for line_text in stop_said + position_proofs(config)[0]:
        print(line_text)
    for warning, line in zip(warnings, file_lines(args.file, warnings), strict=True):
        print(f"{args.file}:{line}: warning: {warning}" if line else f"{args.file}: warning: {warning}",
              file=sys.stderr)
    return 0
