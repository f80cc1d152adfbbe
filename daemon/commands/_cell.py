"""What ``calibrate`` and ``validate`` drive: the config's cell, or the built-in simulated cell.

The command line names the simulated plugin here (the CLI may; the core may not) to apply
``--scenario/--effects/--seed`` over the ``[simulation]`` table, and holds the one seeding rule
(:func:`scenario_seed`) that ``validate``, ``demo`` and ``benchmarks/paper_table1.py`` share.
"""

from __future__ import annotations

import argparse
import functools
import re
from collections.abc import Awaitable, Callable
from typing import Any

from daemon.assembly import procedure_drivers
from daemon.config import ZENOH_KIND, Config, load_config
from daemon.drivers_set import DriverSet
from daemon.errors import UserError
from daemon.procedure.follow import FollowCheck
from daemon.procedure.preflight import check_not_served, wait_for_output
from drivers.simulated.config import SECTION, SimulationConfig
from drivers.simulated.effects import UnknownNameError, resolve_effects
from drivers.simulated.scenarios import get_scenario

_PAPER_TEST = re.compile(r"test(?P<n>[1-9])")


def scenario_seed(seed: int, scenario: str) -> int:
    """The simulated cell's seed for ``scenario`` in a run seeded ``seed``: ``seed * 100 + N`` for the
    paper's test N, ``seed`` itself for calibration and every other scenario.

    The paper's five tests were separate sessions, so each draws its own room fluctuation and sensor
    noise (with one seed for all, the five tests would share their noise sequences). ``validate``,
    ``demo`` and the Table I benchmark all go through this function: the same ``--seed`` gives the
    same Table I figures through each of them.
    """
    match = _PAPER_TEST.fullmatch(scenario)
    return seed * 100 + int(match["n"]) if match else seed


def open_cell(config_path: str | None, args: argparse.Namespace, default_scenario: str,
              start_s: float = 0.0) -> tuple[Config, DriverSet]:
    """The config of ``--config`` (or the built-in simulated cell) and its drivers for a procedure.

    ``--scenario/--effects/--seed`` override the ``[simulation]`` table when given; the seed the
    simulated cell then runs with is :func:`scenario_seed` of that seed and scenario.
    """
    config = load_config(config_path)
    updates: dict[str, Any] = {}
    scenario = getattr(args, "scenario", None) or (default_scenario if config_path is None else None)
    try:
        if scenario:
            get_scenario(scenario)
            updates["scenario"] = scenario
        if getattr(args, "effects", None):
            updates["effects"] = resolve_effects(args.effects)
    except UnknownNameError as err:
        raise UserError(str(err)) from None
    if getattr(args, "seed", None) is not None:
        updates["seed"] = args.seed
    section = config.section(SECTION)
    if isinstance(section, SimulationConfig):
        updates["seed"] = scenario_seed(updates.get("seed", section.seed), updates.get("scenario", section.scenario))
        config = config.with_section(SECTION, section.model_copy(update=updates))
    try:
        return config, procedure_drivers(config, start_s=start_s)
    except ValueError as err:
        raise UserError(f"{config_path or 'built-in config'}: {err}") from None


def guards(config: Config, drivers: DriverSet, args: argparse.Namespace
           ) -> tuple[FollowCheck | None, Callable[[], Awaitable[None]] | None]:
    """What protects a procedure's run: the follow check (every cell), and on hardware the checks
    before it starts. Refuses at once (:class:`~daemon.procedure.preflight.PreflightError`) when a
    daemon serves the cell; returns the output check (``kind = "zenoh"``, unless ``--no-output-check``)
    to run once the drivers are open. The simulated cell on its virtual clock is alone: no checks."""
    settings = config.procedure
    follow = None
    if settings.follow_steps and drivers.position_channel is not None:
        follow = FollowCheck(drivers.position_channel, settings.follow_tolerance, settings.follow_steps)
    if config.virtual_cell:
        return follow, None
    check_not_served(config)
    if config.actuator.kind == ZENOH_KIND and not getattr(args, "no_output_check", False):
        return follow, functools.partial(wait_for_output, config)
    return follow, None
