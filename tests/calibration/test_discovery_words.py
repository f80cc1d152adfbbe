"""Issue 27 item 5: discover's words agree with its table (opening sentence, one expectation per step, flags)."""

from __future__ import annotations

import re

import pytest

from nanodrift.calibration.discovery import discover
from nanodrift.calibration.discovery.candidates import Candidate
from nanodrift.calibration.discovery.confirmation import FreshGain
from nanodrift.calibration.discovery.diagnostics import Disagreement
from nanodrift.calibration.discovery.summary import summarise
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.effects import resolve_effects
from nanodrift.model.identify import fit
from nanodrift.reports.discovery import markdown


@pytest.fixture(scope="module")
def result():
    """The demo's discovery run: a forward-swept model over up-and-down sweeps of a cell with hysteresis."""
    model = fit(simulate_dataset("train", cycles=12, seed=0)).model
    data = simulate_dataset("bidirectional", resolve_effects(["hysteresis"]), cycles=6, seed=0)
    return discover(data, model)


def test_the_opening_sentence_never_denies_structure_it_then_names(result) -> None:
    assert result.steps, "hysteresis hidden in up-and-down sweeps is named"
    first = result.summary.splitlines()[0]
    assert "no significant structure" not in first
    flagged = [d for d in result.disagreements if d.significant]
    assert first.startswith("Residuals track:") == bool(flagged)


def test_a_step_named_where_no_variable_is_flagged_is_said_so_not_denied() -> None:
    """The issue's case: F 731 and η² 0.93 unflagged once deflated, then an effect named at p = 2e-30."""
    unflagged = Disagreement("t", "time since the start of the run (s)", 731.0, 0.39, 1e-30, 0.93, 0.2, [], False)
    step = Candidate("unmonitored_drift", [], [], {"rate_um_per_h": 0.1}, 0, 1, p_value=2e-30,
                     holdout_rms_before_um=0.3, holdout_rms_after_um=0.05,
                     fresh_expected=FreshGain(0.0795, 0.0541, "expected"))
    baseline = {"holdout_rms_um": 0.3}
    final = {"holdout_rms_um": 0.05, "holdout_gap_removed": 0.8, "fresh_rms_expected_um": (0.3711, 0.0541),
             "fresh_gain_expected": 0.15}
    words = summarise([unflagged], [step], baseline, final)
    assert "no significant structure" not in words
    assert words.splitlines()[0].startswith("No single variable's binned residual means differ significantly")
    assert re.findall(r"expect about ([\d.]+) →", words) == ["79.5"]  # one step, one baseline (not 371.1 too)


def test_each_expectation_is_said_once(result) -> None:
    expectations = re.findall(r"expect about ([\d.]+) → ([\d.]+) nm", result.summary)
    assert len(expectations) == (len(result.steps) if len(result.steps) == 1 else len(result.steps) + 1)
    report = markdown(result, [], None)
    # the overall line (the method section's rule 13 uses the same words, so the line is matched whole)
    assert ("- expected on a fresh run of the same kind (rule 13)" in report) == (len(result.steps) > 1)


def test_the_tables_p_and_its_flag_agree(result) -> None:
    report = markdown(result, [], None)
    rows = re.findall(r"^\| (.+?) \| ([\d.e+-]+) \| ([\d.e+-]+) \| ([\d.]+) \| [\d.-]+ \| (yes|no) \|$", report,
                      re.MULTILINE)
    assert len(rows) == len(result.disagreements) > 0
    p_max = result.settings.p_max
    for description, _f, p_shown, eta2, flagged in rows:
        agrees = float(p_shown) < p_max and float(eta2) >= 0.05
        assert agrees == (flagged == "yes"), (description, p_shown, eta2, flagged)
