"""``nanodrift demo``: the paper's whole story on the simulated cell, told truthfully in about a minute.

1. calibrate: the paper's procedure (24 forward sweeps of the ``train`` room) on a virtual clock, then
   stepwise identification -> a model file;
2. validate: the paper's five tests (test 1 without compensation, tests 2-4 inside the training
   range, test 5 outside it), each over the paper's 30 sweeps through the procedure ``nanodrift
   validate`` runs (:func:`nanodrift.procedure.validation.run_validation` on the simulated cell's
   virtual clock), seeded by :func:`nanodrift.commands._cell.scenario_seed` (same seed, same figures);
3. Table I beside the paper's, with a line on each difference (seed, sweeps, the simulated room) and
   on why the static model's test 5 degrades (it extrapolates);
4. serve: ``nanodrift run`` on the calibrated model in its own process on 127.0.0.1 (the room
   running ``--speed`` times faster than real time) and a client sending a few targets over Zenoh,
   as ``nanodrift target`` would; each answer and the position the interferometer then reads;
5. what nanodrift adds beyond the paper (:func:`what_nanodrift_adds`; printed once it has content).

Steps are numbered as they are printed. A bad ``--tests`` value is refused before anything runs. The
daemon's log is kept in ``--keep DIR``, with the figures of ``validate --report`` (fig9, fig11) of the
tests; without it, a failing daemon's last log lines are printed inline (never a path to a file the
demo has deleted).

The simulated cell knows where the stage truly is: each test is also scored against that true
position, beside the interferometer's view (which includes its noise and wander); real hardware has
no such truth.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import itertools
import json
import math
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nanodrift.assembly import simulated_drivers
from nanodrift.atomic import atomic_write_text
from nanodrift.calibration.dataset import DataError
from nanodrift.calibration.discovery import discover
from nanodrift.calibration.iso9283 import TestResult
from nanodrift.calibration.plans import PAPER_TIMING
from nanodrift.calibration.residuals import MIN_RESIDUALS, BiasTracker
from nanodrift.commands._cell import scenario_seed
from nanodrift.commands._demo_serve import serve
from nanodrift.commands._demo_xy import two_axis_part
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.effects import resolve_effects
from nanodrift.drivers.simulated.physics import CELLS
from nanodrift.errors import UserError
from nanodrift.model.equation import equation
from nanodrift.model.identify import FitError
from nanodrift.model.model import Model
from nanodrift.procedure.recording import fit_recorded, record_calibration
from nanodrift.procedure.validation import run_validation
from nanodrift.reports.validation import (
    PAPER_TABLE1,
    provenance_text,
    table1,
    truth_table,
    write_figures,
)

PAPER_CYCLES = 30  # ISO 9283 sweeps per test in the paper
PAPER_CALIBRATION_CYCLES = 24

#: the paper's five tests, what each is (Table I; section III.C)
TESTS: dict[str, str] = {
    "test1": "without compensation (the stage as it is), room inside the training range",
    "test2": "with the model, inside the training range (mild warming)",
    "test3": "with the model, inside the training range (cooling, then warming)",
    "test4": "with the model, inside the training range (warming from its low end)",
    "test5": "with the model, OUTSIDE the training range (the room 0.7 °C warmer and rising)",
}
IN_RANGE = ("test2", "test3", "test4")
#: test 5 "degrades" when its accuracy is more than this times the worst in-range test's (the paper's: 10x)
DEGRADED_FACTOR = 2.0


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "tests (--tests):\n" + "\n".join(f"  {name}  {what}" for name, what in TESTS.items())
    # the demo starts its own daemon (a peer) and client (a client) on loopback; these pick the endpoints
    parser.add_argument("-l", "--listen", action="append", default=[], metavar="EP",
                        help="endpoint the demo's daemon listens on (default: a free port on 127.0.0.1)")
    parser.add_argument("-e", "--connect", action="append", default=[], metavar="EP",
                        help="endpoint the demo's client connects to (default: the --listen endpoint)")
    parser.add_argument("--tests", nargs="+", default=list(TESTS), metavar="T",
                        help="the paper's tests to run: test1 (without compensation), test2-test4 (inside the "
                             "training range), test5 (outside it)")
    parser.add_argument("--cycles", type=int, default=PAPER_CYCLES, metavar="N",
                        help="ISO 9283 validation sweeps per test (the paper: 30)")
    parser.add_argument("--calibration-cycles", type=int, default=PAPER_CALIBRATION_CYCLES, metavar="N",
                        help="calibration sweeps of the 'train' room before the tests (the paper: 24)")
    parser.add_argument("--speed", type=float, default=50.0,
                        help="simulated seconds per wall second of the served cell (the serving step)")
    parser.add_argument("--seed", type=int, default=0, metavar="N",
                        help="simulation seed: the same seed gives the same Table I as validate --seed N")
    parser.add_argument("--cell", choices=list(CELLS), default="realistic",
                        help="the simulated cell: realistic (default: physics no candidate term reproduces, "
                             "drivers/simulated/README.md) or ideal (the drift is exactly the model's form: it shows "
                             "what the method gives when the model can be exact, an upper bound, not a lab's figure). "
                             "The two-axis part and the discovery line stay on the ideal cell")
    parser.add_argument("--keep", metavar="DIR",
                        help="keep the model, data, Table I (JSON), the figures (fig9, fig11; PNG + SVG), config "
                             "and daemon log in DIR")


def check_args(args: argparse.Namespace) -> list[str]:
    """The tests to run, in the paper's order; refuses bad values before anything runs.

    ``--tests test1 test5``, ``--tests test1,test5`` and mixtures name the same tests."""
    asked = [t.strip() for value in args.tests for t in value.split(",") if t.strip()]
    unknown = [t for t in asked if t not in TESTS]
    if unknown:
        raise UserError(f"--tests: unknown test {', '.join(repr(t) for t in unknown)}; "
                        f"valid tests: {', '.join(TESTS)}")
    for flag, value in (("--cycles", args.cycles), ("--calibration-cycles", args.calibration_cycles)):
        if value < 1:
            raise UserError(f"{flag} must be at least 1, got {value}")
    if not args.speed > 0:
        raise UserError(f"--speed must be > 0, got {args.speed}")
    if not asked:
        raise UserError(f"--tests: no test named; valid tests: {', '.join(TESTS)}")
    return [t for t in TESTS if t in asked]


# ----- 1. calibrate ------------------------------------------------------------------------------
def calibrate(workdir: Path, cycles: int, seed: int, cell: str = "ideal") -> Model:
    """The paper's calibration on the simulated cell's virtual clock, fitted as ``nanodrift calibrate`` does."""
    drivers = simulated_drivers("train", seed=scenario_seed(seed, "train"), cell=cell)
    data = workdir / "calibration.csv"
    data.unlink(missing_ok=True)  # --keep DIR reused: a new demo, new data
    asyncio.run(record_calibration(drivers, data, cycles=cycles, progress_stream=io.StringIO()))
    try:
        return fit_recorded(data, workdir / "model.json").models["x"]
    except (FitError, DataError) as err:
        raise UserError(f"the fit of {cycles} calibration sweeps failed: {err}") from None


def training_ranges(model: Model) -> str:
    tr = model.training
    channels = ", ".join(f"{c} {lo:.2f}–{hi:.2f} °C" for c, (lo, hi) in tr.channel_ranges.items())
    return f"x {round(tr.x_range[0])}–{round(tr.x_range[1])} µm" + (f", {channels}" if channels else "")


# ----- 2. validate -------------------------------------------------------------------------------
def validate(model: Model, test: str, cycles: int, seed: int, adapt: BiasTracker | None = None,
             cell: str = "ideal") -> TestResult:
    """One of the paper's tests, exactly as ``nanodrift validate --scenario TEST --seed SEED [--adapt]`` runs it
    (scored against the true position as well, as ``validate`` does on the simulated cell)."""
    drivers = simulated_drivers(test, seed=scenario_seed(seed, test), cell=cell)
    use = None if test == "test1" else model
    return asyncio.run(run_validation(drivers, use, name=test, cycles=cycles, progress_stream=io.StringIO(),
                                      adapt=adapt))


def result_line(result: TestResult) -> str:
    """What one test gave, as the interferometer saw it, then against the true position."""
    true_without, true_with = result.true_accuracy_nm()
    if not result.compensated:
        return (f"accuracy {result.accuracy_without_nm:.0f} nm without compensation (interferometer); "
                f"{true_without:.0f} nm against the true position")
    line = (f"accuracy {result.accuracy_nm:.0f} nm with the model, {result.accuracy_without_nm:.0f} nm without "
            f"(computed); {result.improvement:.1f}× better (interferometer); against the true position "
            f"{true_with:.0f} nm with, {true_without:.0f} nm without")
    total = len(result.steps)
    if result.extrapolating_steps:
        line += f"; {result.extrapolating_steps} of {total} steps outside the training range"
    elif total:
        line += "; no step outside the training range"
    return line


# ----- 3. Table I beside the paper's ----------------------------------------------------------------
def _exceedance(model: Model, result: TestResult) -> tuple[str, float, float, float, float] | None:
    """The channel that left the training range furthest: (channel, reached °C, by °C, low, high)."""
    worst: tuple[str, float, float, float, float] | None = None
    for channel, (lo, hi) in model.training.channel_ranges.items():
        values = [s.temperatures[channel] for s in result.steps if channel in s.temperatures]
        if not values:
            continue
        top, bottom = max(values), min(values)
        reached, by = (top, top - hi) if top - hi >= lo - bottom else (bottom, lo - bottom)
        if by > 0 and (worst is None or by > worst[2]):
            worst = (channel, reached, by, lo, hi)
    return worst


def nm_span(values: Sequence[float]) -> str:
    """``38–91 nm``, or ``38 nm`` when the rounded ends agree (one test, or equal figures)."""
    low, high = f"{min(values):.0f}", f"{max(values):.0f}"
    return f"{low} nm" if low == high else f"{low}–{high} nm"


def explain(results: Sequence[TestResult], model: Model, args: argparse.Namespace) -> list[str]:
    """One line per difference from the paper, and why test 5 degrades."""
    lines = []
    why = ["the room is simulated (scenarios after the paper's Fig. 10, not its lab's recorded temperatures)",
           f"the noise is drawn from --seed {args.seed} (another seed gives other figures; "
           "benchmarks/paper_table1.py --seeds shows the spread)"]
    if args.cycles != PAPER_CYCLES:
        why.append(f"only {args.cycles} of the paper's {PAPER_CYCLES} sweeps per test (means over fewer visits, "
                   "a shorter window of the room's history)")
    if args.calibration_cycles != PAPER_CALIBRATION_CYCLES:
        why.append(f"a calibration of {args.calibration_cycles} sweeps, not the paper's {PAPER_CALIBRATION_CYCLES}")
    lines.append("Differences from the paper: " + "; ".join(why) + ".")
    by_name = {r.name: r for r in results}
    outside = [r for r in results if r.name in IN_RANGE and r.extrapolating_steps]
    if outside:
        seen = training_ranges(model)
        lines.append(f"{', '.join(r.name for r in outside)} should stay inside the training range, but this model was "
                     f"trained on {seen} only ({args.calibration_cycles} calibration sweeps), so "
                     f"{sum(r.extrapolating_steps for r in outside)} steps extrapolate.")
    test5 = by_name.get("test5")
    if test5 is not None:
        def accuracy(r: TestResult) -> float:  # the truth where the cell knows it: no interferometer wander
            return r.accuracy_true_nm if r.has_truth else r.accuracy_nm

        basis = " against the true position" if test5.has_truth else ""
        in_range = [accuracy(by_name[t]) for t in IN_RANGE if t in by_name]
        paper_in = [PAPER_TABLE1[t][1] or math.nan for t in IN_RANGE]
        out = _exceedance(model, test5)
        where = (f"{out[0]} reached {out[1]:.2f} °C, {out[2]:.2f} °C beyond the training range "
                 f"{out[3]:.2f}–{out[4]:.2f} °C" if out else "outside the training range")
        ours = (f"{accuracy(test5):.0f} nm against {nm_span(in_range)} in range{basis}"
                if in_range else f"{accuracy(test5):.0f} nm{basis}")
        paper = f"{PAPER_TABLE1['test5'][1]:.0f} nm against {nm_span(paper_in)} in range"
        if not in_range or accuracy(test5) > DEGRADED_FACTOR * max(in_range):
            lines.append(f"Test 5 degrades because the static model extrapolates ({where}): {ours}; the paper's "
                         f"test 5 shows the same ({paper}).")
        else:
            lines.append(f"Test 5 extrapolates ({where}) yet stays within {DEGRADED_FACTOR:g}× of in range on this "
                         f"seed: {ours}; the paper's test 5 degraded ({paper}).")
    lines += seed_luck(results, args.cell, args.seed)
    return lines


#: the command that measured :data:`SEED_SPREAD_X` (per cell); the demo computes nothing over seeds itself
SEED_SPREAD_COMMAND = "python benchmarks/paper_table1.py --seeds 16 --cell {cell}"
#: per cell and test, the improvement against the true position (AP without / AP with) over seeds 0..15 of
#: :data:`SEED_SPREAD_COMMAND` (its vectorised simulator: the demo's physics, plan and fit without asyncio):
#: (median, 5th percentile, 95th percentile), as its "seed luck" lines print them
SEED_SPREAD_X: dict[str, dict[str, tuple[float, float, float]]] = {
    "realistic": {"test2": (8.2, 3.2, 13.4), "test3": (10.1, 3.4, 15.3), "test4": (8.0, 3.3, 15.0),
                  "test5": (3.4, 2.3, 6.6)},
    "ideal": {"test2": (39.4, 11.9, 299.5), "test3": (30.4, 15.3, 464.7), "test4": (31.9, 12.3, 255.1),
              "test5": (2.8, 2.3, 4.2)},
}


def seed_luck(results: Sequence[TestResult], cell: str, seed: int) -> list[str]:
    """This seed's improvements against the truth beside their distribution over 16 seeds (precomputed)."""
    spread = SEED_SPREAD_X.get(cell, {})
    parts = []
    for r in results:
        if r.name not in spread or not r.compensated or not r.has_truth:
            continue
        without, with_ = r.true_accuracy_nm()
        median, low, high = spread[r.name]
        parts.append(f"{r.name} is {without / with_:.1f}× against the true position (over 16 seeds: median "
                     f"{median:.1f}×, 90 % of seeds {low:.1f}–{high:.1f}×)")
    if not parts:
        return []
    return [f"Seed luck: seed {seed}'s " + "; ".join(parts) + f". One seed is one draw of the room and the noise "
            f"(`{SEED_SPREAD_COMMAND.format(cell=cell)}`)."]


# ----- 5. what nanodrift adds ------------------------------------------------------------------------
#: what the bias tracker costs, said beside what it gives
ADAPTATION_NEEDS = ("adaptation needs the interferometer (a position sensor) kept in service: the bias tracker "
                    "feeds on its settled residuals; the paper's method needs it only to calibrate, then compensates "
                    "from the temperatures alone")
#: the discovery line's run: the train room swept up and down, with an effect the forward sweeps cannot show
DISCOVERY_SCENARIO, DISCOVERY_EFFECT, DISCOVERY_CYCLES = "bidirectional", "hysteresis", 6


def discovery_line(model: Model, seed: int) -> str:
    """``nanodrift discover`` with the calibrated model on a short run of a cell with an effect hidden."""
    t0 = time.monotonic()
    seed = scenario_seed(seed, DISCOVERY_SCENARIO)  # as `nanodrift simulate --seed` takes it
    data = simulate_dataset(DISCOVERY_SCENARIO, resolve_effects([DISCOVERY_EFFECT]), cycles=DISCOVERY_CYCLES,
                            seed=seed)
    result = discover(data, model)
    run = (f"discovery: `nanodrift discover` runs the model above over {DISCOVERY_CYCLES} up-and-down sweeps of a "
           f"cell with {DISCOVERY_EFFECT} hidden (`nanodrift simulate --scenario {DISCOVERY_SCENARIO} --effects "
           f"{DISCOVERY_EFFECT} --cycles {DISCOVERY_CYCLES} --seed {seed}`): ")
    took = f" ({time.monotonic() - t0:.1f} s)"
    if not result.steps:
        return run + "nothing found" + took
    named = ", then ".join(f"{s.effect} (term {', '.join(t.name for t in s.add) or 'none'}, p = {s.p_value:.0e})"
                           for s in result.steps)
    return (run + f"it names {named}; the held-out RMS falls from {result.baseline['holdout_rms_um'] * 1000:.0f} "
            f"to {result.final['holdout_rms_um'] * 1000:.0f} nm" + took)


def adapted_sigma_words(static: TestResult, adapted: TestResult) -> str:
    """The σ of the corrected commands (``q_sigma_adapted_um``) beside the model's, and what it held."""
    if not (adapted.q_sigma_adapted_um and static.q_sigma_um):
        return ""
    held = adapted.coverage_true() if adapted.has_truth else adapted.coverage()
    return (f"; the corrected commands' σ (q_sigma_adapted_um, what the tracker leaves) median "
            f"{np.median(adapted.q_sigma_adapted_um) * 1000:.0f} nm against the model's "
            f"{np.median(static.q_sigma_um) * 1000:.0f} nm, holding {held * 100:.0f} % of the "
            f"{'true ' if adapted.has_truth else ''}errors within ±2σ")


def what_nanodrift_adds(args: argparse.Namespace, model: Model, results: Sequence[TestResult],
                        served: Sequence[dict[str, Any]]) -> list[str]:
    """What the service adds beyond the paper's static model, shown on the same tests and seed: adaptation
    (``validate --adapt``'s bias tracker on the out-of-range test and one in range), discovery
    (:func:`discovery_line`), the per-command uncertainty (how often the true error lay within ±2σ) and the
    serving daemon's ``health`` (:func:`health_line`)."""
    tracker_defaults = (600.0, 1.0)  # [adapt] tau_s, max_um
    lines: list[str] = []
    by_name = {r.name: r for r in results}
    for test in ("test5", "test2"):
        static = by_name.get(test)
        if static is None:
            continue
        adapted = validate(model, test, args.cycles, args.seed, adapt=BiasTracker(*tracker_defaults), cell=args.cell)
        lines.append(f"adaptation on {test} ([adapt] mode = \"bias\", tau_s {tracker_defaults[0]:g} s): "
                     f"{static.accuracy_nm:.0f} nm static -> {adapted.accuracy_nm:.0f} nm adaptive "
                     f"({adapted.improvement:.1f}× against {static.improvement:.1f}×) as the interferometer the "
                     f"tracker follows sees it, {static.accuracy_true_nm:.0f} nm -> {adapted.accuracy_true_nm:.0f} nm "
                     f"against the true position; the correction ended at "
                     f"{adapted.corrections_um[-1] * 1000:+.0f} nm" + adapted_sigma_words(static, adapted))
    if lines:  # an adaptation line (the only lines so far)
        lines.append(ADAPTATION_NEEDS)
    lines.append(discovery_line(model, args.seed))
    covered = [r for r in results if r.compensated and r.q_sigma_um]
    if covered:
        held = [r.coverage_true() if r.has_truth else r.coverage() for r in covered]
        shares = ", ".join(f"{r.name} {share * 100:.0f} %" for r, share in zip(covered, held, strict=True))
        lines.append(f"uncertainty: every command carries q_sigma_um; the {'true ' if covered[0].has_truth else ''}"
                     f"error lay within ±2σ in {shares} of the steps (it grows outside the training range; a "
                     "calibrated σ keeps 90-98 %)")
        if any(not 0.90 <= share <= 0.98 for share in held):
            lines.append("   not calibrated on this seed: most of a run's error is one offset its steps share (the "
                         "calibration's coefficients are off the same way for all of them), so a run is inside ±2σ "
                         "almost whole or not at all; σ is set to err wide (benchmarks/adaptation.py: 8 seeds)")
    health = next((a["health"] for a in reversed(served) if isinstance(a.get("health"), dict)), None)
    if health is not None:
        lines.append(health_line(health))
    return lines


def health_line(health: dict[str, Any]) -> str:
    """The serving daemon's ``health`` (from its ``status``), measured on the targets of the serve step."""
    n = health.get("n") or 0
    line = f"health, from the serving daemon's status: {health.get('state')} after {n} settled residual(s)"
    if n < MIN_RESIDUALS:
        line += f" (it judges from {MIN_RESIDUALS} on)"
    mean, rms = health.get("residual_mean_nm"), health.get("residual_rms_nm")
    if mean is not None and rms is not None:
        line += f"; residual (interferometer - target) mean {mean:+.0f} nm, RMS {rms:.0f} nm"
    if health.get("advice"):
        line += f"; advice: {health['advice']}"
    return line


def keep_figures(args: argparse.Namespace, workdir: Path, model: Model, results: Sequence[TestResult]) -> list[Path]:
    """fig9 and fig11 of the tests into the kept folder (the PNGs listed; each has an SVG beside it)."""
    tests = ", ".join(r.name for r in results)
    cell = (f"simulated {args.cell} cell: {tests}, --seed {args.seed}, {args.cycles} sweeps "
            f"(nanodrift demo --cell {args.cell})")
    written = write_figures(results, workdir, training=model.training,
                            provenance=provenance_text(model.id, model.provenance.get("data_file"), cell))
    return [path for path in written if path.suffix == ".png"]


def cell_config(cell: str, keep: Path | None) -> str:
    """What ``validate`` needs to run the demo's cell: nothing for the ideal one (its built-in default), else a
    config naming the cell, written into the kept folder (``keep``; None: the folder --keep would give)."""
    if cell == "ideal":
        return ""
    if keep is None:
        return f" --config DIR/{cell}.toml"
    path = keep / f"{cell}.toml"
    atomic_write_text(path, f'# the simulated cell of `nanodrift demo --cell {cell}`\n[simulation]\ncell = "{cell}"\n')
    return f" --config {path}"


# ----- the story -----------------------------------------------------------------------------------
def main(args: argparse.Namespace) -> int:
    tests = check_args(args)
    started = time.monotonic()
    keep = args.keep
    with tempfile.TemporaryDirectory(prefix="nanodrift-demo-") as tmp:
        workdir = (Path(keep) if keep else Path(tmp)).resolve()  # the daemon runs with cwd=workdir
        workdir.mkdir(parents=True, exist_ok=True)
        results: list[TestResult] = []
        numbers = itertools.count(1)

        def step(title: str) -> None:  # numbered as they are printed
            print(f"\n{next(numbers)}. {title}", flush=True)

        realistic = "" if args.cell == "ideal" else f"{args.cell} "
        print(f"nanodrift demo: the paper's calibration and its tests on the simulated {realistic}cell "
              f"(seed {args.seed})")

        step(f"Calibrate: {args.calibration_cycles} forward sweeps of the 'train' room, 0–480 µm by 30 µm "
                    f"(~{args.calibration_cycles * 17 * PAPER_TIMING.step_s / 3600:.1f} h of simulated time on a "
                    "virtual clock), then stepwise identification")
        t0 = time.monotonic()
        model = calibrate(workdir, args.calibration_cycles, args.seed, args.cell)
        print(f"   model {model.id}: {equation(model)}")
        print(f"   trained on {training_ranges(model)}; residual "
              f"{model.fit.get('residual_rms_nm', math.nan):.1f} nm RMS ({time.monotonic() - t0:.1f} s)")

        step(f"Validate: the paper's tests, ISO 9283 over {args.cycles} sweeps of 0–480 µm by 80 µm each, "
                    "as `nanodrift validate` runs them")
        for test in tests:
            t0 = time.monotonic()
            result = validate(model, test, args.cycles, args.seed, cell=args.cell)
            results.append(result)
            print(f"   {test}: {TESTS[test]}\n          {result_line(result)} ({time.monotonic() - t0:.1f} s)",
                  flush=True)

        step("Table I, beside the paper's")
        print(table1(results, paper=PAPER_TABLE1))
        truth = truth_table(results)
        if truth:
            print(f"\n{truth}\n")
        for line in explain(results, model, args):
            print(line)
        if keep:
            atomic_write_text(workdir / "table1.json", json.dumps(
                {"tests": [r.to_dict() for r in results], "model": model.id, "seed": args.seed,
                 "cycles": args.cycles, "calibration_cycles": args.calibration_cycles}, indent=2) + "\n")
            figures = keep_figures(args, workdir, model, results)
            print(f"Figures (PNG + SVG, as validate --report draws them): {', '.join(str(f) for f in figures)}")
            print(f"The same figures from the command line, e.g.: nanodrift validate --model {workdir / 'model.json'} "
                  f"--scenario {tests[-1]} --seed {args.seed} --cycles {args.cycles}"
                  f"{cell_config(args.cell, workdir)}")
        else:
            print("The same figures from the command line: keep the model with --keep DIR, then "
                  "nanodrift validate --model DIR/model.json --scenario testN --seed "
                  f"{args.seed} --cycles {args.cycles}{cell_config(args.cell, None)}")

        step("Serve: the calibrated model behind the daemon, targets from a client over Zenoh")
        served = serve(args, workdir, workdir / "model.json", bool(keep))

        extra = what_nanodrift_adds(args, model, results, served)
        step("What nanodrift adds")
        for line in extra:
            print(f"   {line}")
        t0 = time.monotonic()
        print("   two axes: an XY stage calibrated and validated as one cell (the paper's future work, its follow-up's "
              "2-DoF case), as `simulate --axes xy`, `fit` and `validate` do it:")
        for line in two_axis_part(args.seed, args.cycles, args.calibration_cycles, workdir if keep else None):
            print(f"      {line}")
        print(f"      ({time.monotonic() - t0:.1f} s)")

        where = (f"files in {workdir}" if keep
                 else "nothing kept (--keep DIR keeps the model, data, figures, config and log)")
        print(f"\n(demo took {time.monotonic() - started:.0f} s; {where})")
    return 0
