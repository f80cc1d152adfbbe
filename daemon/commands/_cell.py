"""What ``calibrate`` and ``validate`` drive: the config's cell, or the built-in simulated cell.

The options that choose it are declared here (``--config``, the ``--scenario/--effects/--seed``
overrides of the simulated cell, ``--no-output-check``) beside the code that reads them. The command
line names the simulated plugin here (the CLI may; the core may not) to apply the overrides over the
``[simulation]`` table, and holds the one seeding rule (:func:`scenario_seed`) that ``validate``,
``demo`` and ``benchmarks/paper_table1.py`` share.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import re
import signal
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

from nanodrift.assembly import procedure_drivers
from nanodrift.commands._catalogues import effect_names, scenario_epilog, scenario_names
from nanodrift.commands._config_flag import add_config_flag
from nanodrift.config import ZENOH_KIND, Config, load_config
from nanodrift.drivers.simulated.config import SECTION, SimulationConfig
from nanodrift.drivers.simulated.effects import UnknownNameError, resolve_effects
from nanodrift.drivers.simulated.scenarios import get_scenario
from nanodrift.drivers_set import DriverSet
from nanodrift.errors import UserError, user_errors
from nanodrift.procedure.follow import FollowCheck
from nanodrift.procedure.preflight import check_not_served, wait_for_output

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


def add_procedure_flags(parser: argparse.ArgumentParser, default_scenario: str, *, several: bool = False,
                        over_config: bool = False) -> None:
    """What every procedure on a cell takes: ``--config F``, ``--no-output-check`` (on hardware with
    ``kind = "zenoh"`` a procedure refuses to start with nobody applying the steps) and, for the simulated cell
    (no --config, or a config with simulated sensors), ``--scenario/--effects/--seed`` over [simulation].

    ``several``: ``--scenario`` may name several rooms, comma-separated or repeated (a list, read with
    :func:`scenario_list`), each run in turn. ``over_config``: ``default_scenario`` applies with a config
    too (see :func:`open_cell`)."""
    parser.epilog = scenario_epilog()
    add_config_flag(parser)
    default = (f"{default_scenario}, whatever the config's [simulation] scenario (the room the daemon serves in)"
               if over_config else f"{default_scenario} with no --config, else the config's [simulation] scenario")
    each = ("; several, comma-separated or repeated (--scenario test2,test3 or --scenario test2 --scenario test3), "
            "are run in turn into one report") if several else ""
    parser.add_argument("--scenario", metavar="S", action="append" if several else "store",
                        help=f"simulated room history, one of {scenario_names()}{each} (default: {default})")
    parser.add_argument("--effects", metavar="a,b",
                        help=f"hidden effects of the simulated cell, from {effect_names()} "
                             "(default: none, or the config's)")
    parser.add_argument("--seed", type=int, metavar="N",
                        help="simulation seed (default: 0, or the config's); the paper's test N runs with "
                             "seed*100+N, as in demo")
    parser.add_argument("--no-output-check", action="store_true",
                        help="start even when no output node is subscribed to nanodrift/<cell>/command")


def scenario_list(values: list[str] | None) -> list[str]:
    """``--scenario`` given several times or comma-separated, in order, each once (empty: none given)."""
    names = [name.strip() for value in values or [] for name in value.split(",") if name.strip()]
    return list(dict.fromkeys(names))


def open_cell(args: argparse.Namespace, default_scenario: str, start_s: float = 0.0, *,
              over_config: bool = False, config: Config | None = None) -> tuple[Config, DriverSet]:
    """The config of ``--config`` (or the built-in simulated cell, or ``config`` when given) and its drivers for
    a procedure.

    ``--scenario/--effects/--seed`` override the ``[simulation]`` table when given; the seed the
    simulated cell then runs with is :func:`scenario_seed` of that seed and scenario. Without
    ``--scenario`` the simulated room is ``default_scenario`` with no config; with one, the config's
    ``[simulation] scenario``, unless ``over_config`` (calibrate: the config's scenario is the room the
    daemon serves in, and a calibration needs the paper's training room, whatever the daemon serves in).
    """
    config = config or load_config(args.config)
    updates: dict[str, Any] = {}
    scenario = args.scenario or (default_scenario if args.config is None or over_config else None)
    with user_errors(UnknownNameError):
        if scenario:
            get_scenario(scenario)
            updates["scenario"] = scenario
        if args.effects:
            updates["effects"] = resolve_effects(args.effects)
    if args.seed is not None:
        updates["seed"] = args.seed
    section = config.section(SECTION)
    if isinstance(section, SimulationConfig):
        updates["seed"] = scenario_seed(updates.get("seed", section.seed), updates.get("scenario", section.scenario))
        config = config.with_section(SECTION, section.model_copy(update=updates))
    try:
        return config, procedure_drivers(config, start_s=start_s)
    except ValueError as err:
        raise UserError(f"{config.source}: {err}") from None


#: with several axes, an axis' move shorter than this is not follow-checked: the other axes' moves push it by up
#: to a couple of micrometres on a stacked stage (crosstalk and non-orthogonality: ~0.4 % of their travel)
CELL_FOLLOW_MIN_MOVE_UM = 10.0


def guards(config: Config, drivers: DriverSet, args: argparse.Namespace
           ) -> tuple[dict[str, FollowCheck], Callable[[], Awaitable[None]] | None]:
    """What protects a procedure's run: a follow check per axis on its own position sensor (every cell; none
    when ``[procedure] follow_steps = 0``), and on hardware the checks before it starts. Refuses at once
    (:class:`~nanodrift.procedure.preflight.PreflightError`) when a daemon serves the cell; returns the
    output check (``kind = "zenoh"``, unless ``--no-output-check``) to run once the drivers are open. The
    simulated cell on its virtual clock is alone: no checks."""
    settings = config.procedure
    min_move_um = 1.0 if len(config.axis_names) == 1 else CELL_FOLLOW_MIN_MOVE_UM
    follow = {axis: FollowCheck(drivers.position_axes[axis], settings.follow_tolerance, settings.follow_steps,
                                min_move_um=min_move_um)
              for axis in config.axis_names if settings.follow_steps and axis in drivers.position_axes}
    if config.virtual_cell:
        return follow, None
    check_not_served(config)
    published = any(actuator.kind == ZENOH_KIND for actuator in config.axis_actuators().values())
    if published and not args.no_output_check:
        return follow, functools.partial(wait_for_output, config)
    return follow, None


T = TypeVar("T")


def run_procedure(procedure: Coroutine[Any, Any, T]) -> T:
    """Run a procedure on the cell (``asyncio.run``) so that Ctrl-C always ends it as ``KeyboardInterrupt``.

    ``asyncio.run`` turns SIGINT into a cancellation of the procedure, and Python 3.11 can lose a
    cancellation (``asyncio.wait_for`` returns a result that completed as it was cancelled): a calibration
    interrupted at step 17 of 3400 then returned as if complete, and its few steps were fitted into a model
    (seen once in a loaded test run). So SIGINT is also remembered here, and a procedure that returns after
    one raises ``KeyboardInterrupt`` all the same: the caller keeps its steps and prints how to resume.
    """
    interrupted: list[bool] = []

    async def guarded() -> T:
        task = asyncio.current_task()
        assert task is not None
        loop = asyncio.get_running_loop()

        def on_sigint() -> None:
            interrupted.append(True)
            task.cancel()

        loop.add_signal_handler(signal.SIGINT, on_sigint)
        try:
            return await procedure
        finally:
            loop.remove_signal_handler(signal.SIGINT)

    try:
        result = asyncio.run(guarded())
    except asyncio.CancelledError:
        if interrupted:
            raise KeyboardInterrupt from None
        raise
    if interrupted:
        raise KeyboardInterrupt
    return result
