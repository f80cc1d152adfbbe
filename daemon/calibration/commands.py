"""``nanodrift simulate``, ``calibrate`` and ``validate``: the procedures on the configured backend.

With no ``--config`` the backend is the simulated cell on a virtual clock (a 4-hour calibration in
seconds); ``--scenario/--effects/--seed`` choose its room history and hidden effects.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from daemon.calibration.procedure import (
    Backend,
    bidirectional_plan,
    calibration_columns,
    calibration_plan,
    completed_steps,
    config_backend,
    fit_recorded,
    record_calibration,
    resume_hint,
)
from daemon.errors import UserError


def open_backend(config_path: str | None, args: argparse.Namespace, default_scenario: str,
                 start_s: float = 0.0) -> Backend:
    """The backend of ``--config`` (daemon.config.load_config), or the built-in simulated cell.

    ``--scenario/--effects/--seed`` override the ``[simulation]`` table when given.
    """
    from daemon.config import load_config
    from drivers.simulated.effects import UnknownNameError, resolve_effects
    from drivers.simulated.scenarios import get_scenario

    config = load_config(config_path)
    sim = config.simulation
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
    if updates:
        config = config.model_copy(update={"simulation": sim.model_copy(update=updates)})
    try:
        return config_backend(config, start_s=start_s)
    except ValueError as err:
        raise UserError(f"{config_path or 'built-in config'}: {err}") from None


# ----- simulate ----------------------------------------------------------------------------------------


def simulate_command(args: argparse.Namespace) -> int:
    from daemon.calibration.dataset import write_csv
    from drivers.simulated.datasets import simulate_dataset
    from drivers.simulated.effects import UnknownNameError, resolve_effects

    if args.cycles is not None and args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    try:
        effects = resolve_effects(args.effects or None)
        ds = simulate_dataset(args.scenario, effects, cycles=args.cycles, seed=args.seed)
    except UnknownNameError as err:
        raise UserError(str(err)) from None
    write_csv(ds, args.out)
    cycles = ds.extra["cycle"]
    span = (ds.t[-1] - ds.t[0]) / 3600.0
    print(f"wrote {args.out}: {len(ds)} steps ({len(ds) // max(1, len(set(cycles.tolist())))} per cycle, "
          f"{span:.2f} h), scenario {args.scenario}, effects {','.join(effects) or 'none'}, seed {args.seed}",
          file=sys.stderr)
    return 0


# ----- calibrate ---------------------------------------------------------------------------------------


def _data_path(args: argparse.Namespace) -> Path:
    if args.data:
        return Path(args.data)
    out = Path(args.out)
    return out.with_name(out.stem + "_data.csv")


def calibrate_command(args: argparse.Namespace) -> int:
    from daemon.calibration.dataset import DataError

    if args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    data = _data_path(args)
    if args.resume:
        if not data.exists():
            raise UserError(f"--resume: {data} does not exist (nothing to continue)")
    elif data.exists() and data.stat().st_size > 0:
        raise UserError(f"{data} already holds recorded steps; continue it with --resume, or choose another --data")
    backend = open_backend(args.config, args, "train")
    columns = calibration_columns(backend)
    plan = (bidirectional_plan if _is_bidirectional(args) else calibration_plan)(args.cycles)
    try:
        done, last_t = completed_steps(data, columns) if args.resume else (0, 0.0)
    except DataError as err:
        raise UserError(str(err)) from None
    if args.resume and backend.simulated_cell is not None and done:
        backend = open_backend(args.config, args, "train", start_s=last_t + 1.0)
    print(f"calibration on {backend.description}: {len(plan)} steps ({args.cycles} cycles), data -> {data}"
          + (f", resuming after {done} recorded steps" if done else ""), file=sys.stderr)
    try:
        asyncio.run(record_calibration(backend, data, plan=plan, resume=args.resume))
    except (KeyboardInterrupt, Exception) as err:
        recorded = completed_steps(data, columns)[0] if data.exists() else 0
        print(resume_hint(args.out, data, recorded, len(plan)), file=sys.stderr)
        if isinstance(err, FileExistsError | DataError):
            raise UserError(str(err)) from None
        raise
    from daemon.model.identify import FitError

    try:
        result = fit_recorded(data, args.out)
    except (FitError, DataError) as err:
        raise UserError(f"the recorded steps in {data} are kept, but the fit failed: {err}") from None
    model = result.model
    terms = " + ".join(f"{ft.coef:+.4g}*{ft.term.name}" for ft in model.terms)
    print(f"model -> {args.out}: q = {terms}", file=sys.stderr)
    residual = model.fit.get("residual_rms_nm", float("nan"))
    print(f"fit residual {residual:.1f} nm RMS over {model.fit.get('rows')} steps", file=sys.stderr)
    return 0


def _is_bidirectional(args: argparse.Namespace) -> bool:
    return getattr(args, "scenario", None) == "bidirectional"


# ----- validate ----------------------------------------------------------------------------------------


def validate_command(args: argparse.Namespace) -> int:
    from daemon.calibration.report import table1, write_report
    from daemon.calibration.validation import run_validation
    from daemon.model.model import ModelFileError, load_model

    if args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    try:
        model = load_model(args.model)
    except (ModelFileError, OSError) as err:
        raise UserError(str(err)) from None
    backend = open_backend(args.config, args, "test2")
    name = getattr(args, "scenario", None) or ("test2" if args.config is None else "validation")
    compensate = not getattr(args, "no_compensation", False)
    try:
        result = asyncio.run(run_validation(backend, model if compensate else None, name=name, cycles=args.cycles))
    except ValueError as err:
        raise UserError(str(err)) from None
    text = table1([result])
    doc: dict[str, Any] = {"model": model.id, "backend": backend.description, "cycles": args.cycles,
                           **result.to_dict()}
    if args.report:
        files = write_report([result], args.report, text, doc)
        print(f"report: {', '.join(str(f) for f in files)}", file=sys.stderr)
    if args.json:
        print(json.dumps(doc, indent=2, default=_json_default))
    else:
        print(text)
        print(f"\nper point ({'with compensation' if compensate else 'without compensation'}):")
        for p in result.points:
            acc, rep = (p.accuracy_nm, p.repeatability_nm) if compensate else (p.accuracy_without_nm,
                                                                                 p.repeatability_without_nm)
            print(f"  x' = {p.target_um:5.0f} um: accuracy {acc:7.1f} nm, repeatability {rep:7.1f} nm "
                  f"({p.visits} visits)")
    return 0


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
