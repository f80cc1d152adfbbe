"""The finding in words, for the operator: what the residuals track and what each named step did."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from nanodrift.calibration.discovery.candidates import Candidate
from nanodrift.calibration.discovery.diagnostics import Disagreement


def _describe(c: Candidate) -> str:
    p = c.params
    if c.effect == "thermal_lag":
        return (f"a first-order thermal lag of {p['tau_s'] / 60:.0f} min on {p['channel']} (term {c.add[-1].name}; "
                f"about {p['tau_behind_fastest_s'] / 60:.0f} min behind the fastest channel)")
    if c.effect == "temperature_rate":
        return f"the rate of change of {p['channel']}, smoothed over {p['tau_s']:.0f} s (term {c.add[-1].name})"
    if c.effect == "creep":
        return f"creep after each step with a time constant of {p['tau_s']:g} s (term {c.add[0].name})"
    if c.effect == "hysteresis":
        return "hysteresis: an offset that depends on the direction of approach (term dir)"
    if c.effect == "position_thermal_coupling":
        return f"a position-thermal coupling, the stage's gain changing with {p['channel']} (term {c.add[0].name})"
    if c.effect == "geometric_order":
        return f"a higher geometric order (term {c.add[0].name})"
    if c.effect == "unmonitored_drift":
        return (f"a drift of {p.get('rate_um_per_h', 0):+.3f} µm/h that no sensor explains (not applied online: "
                "add a sensor near its source, e.g. the interferometer's dead path)")
    if c.effect == "missing_channel":
        return f"channel {p['channel']}, which the model had left out (term {p['channel']})"
    if c.effect == "sensor_exclusion":
        return f"leaving out channel {p['channel']}, which fits the training blocks but hurts held-out ones"
    if c.effect == "crosstalk":
        return (f"crosstalk from axis {p['axis']}: this axis moves with {p['axis']}'s position (actuator coupling "
                f"or axes that are not orthogonal; term {c.add[0].name})")
    if c.effect == "coupled_bending":
        return f"coupled bending: the stage bends when both axes are out (term {c.add[0].name})"
    return c.effect


def summarise(disagreements: Sequence[Disagreement], steps: Sequence[Candidate], baseline: Mapping[str, Any],
              final: Mapping[str, Any], untestable: Sequence[Mapping[str, str]] = ()) -> str:
    """The finding in words, for the operator; then what this run could not test, and how to test it."""
    lines = []
    top = [d for d in disagreements if d.significant][:3]
    if top:
        where = "; ".join(f"{d.description} (bins differ by {d.spread_um * 1000:.0f} nm, p = {d.p_value:.1g})"
                          for d in top)
        lines.append(f"Residuals track: {where}.")
    elif steps:  # rule 1's binned means and rule 2's partial F-test are different tests: say which said what
        lines.append("No single variable's binned residual means differ significantly once the residuals' "
                     "autocorrelation is allowed for (rule 1); a candidate term still clears the bar (rule 2):")
    else:
        lines.append("Residuals show no significant structure against time, position, temperatures, "
                     "their rates, direction or steps.")
    if not steps:
        lines.append(f"No missing effect clears the bar; the model stands "
                     f"(held-out RMS {baseline['holdout_rms_um'] * 1000:.1f} nm).")
    for i, s in enumerate(steps, 1):
        lines.append(
            f"Step {i}: {_describe(s)} cuts the held-out RMS from {s.holdout_rms_before_um * 1000:.1f} to "
            f"{s.holdout_rms_after_um * 1000:.1f} nm ({100 * s.holdout_gain:.0f} % of the gap; p = {s.bar_p:.1g})."
        )
        lines += _fresh_lines(s)
        if s.tau_range is not None:
            words = s.tau_range.words() + " (held-out blocks not significantly worse than at the τ named)"
            if "tau_behind_fastest_s" in s.params:
                shift = float(s.params["tau_behind_fastest_s"]) - float(s.params["tau_s"])
                lo, hi = s.tau_range.lo_s + shift, s.tau_range.hi_s + shift
                words += (f"; behind the fastest channel about {lo / 60:.0f}–{hi / 60:.0f} min (delays in series "
                          "add only approximately)")
            lines.append(f"  Time constant: {words}.")
        if math.isfinite(s.holdout_rms_nested_um):
            lines.append(f"  Chosen without each held-out block, τ predicts the blocks to "
                         f"{s.holdout_rms_nested_um * 1000:.1f} nm RMS ({s.holdout_rms_after_um * 1000:.1f} nm when "
                         "chosen on all rows).")
        if s.params.get("alike"):
            lines.append(f"  In this run it looks like {s.params['alike']} (their columns correlate "
                         f"{s.params['alike_correlation']:.2f} beyond the model's terms: the room fell and rose "
                         "once), so the two are told apart by noise and a time constant is not pinned; a longer "
                         "run, in which the room settles, tells them apart.")
        if s.params.get("readmitted"):
            lines.append(f"  With it in, the model's own selection re-admits {', '.join(s.params['readmitted'])}, "
                         "which the hidden effect had masked.")
    if steps:
        lines.append(
            f"Overall the held-out RMS went from {baseline['holdout_rms_um'] * 1000:.1f} to "
            f"{final['holdout_rms_um'] * 1000:.1f} nm ({100 * final['holdout_gap_removed']:.0f} % removed)."
        )
        if "fresh_gain_expected" in final and len(steps) > 1:  # one step has said its own expectation
            before, after = final["fresh_rms_expected_um"]
            lines.append(f"From the given model as it is (its own coefficients; step 1 starts from its terms refitted "
                         f"on this run), on a fresh run of the same kind expect about {_nm(before, after)} "
                         f"(RMS × {final['fresh_gain_expected']:.2f})"
                         + (f"; measured on the fresh run given: {_nm(*final['fresh_rms_measured_um'])} "
                            f"(× {final['fresh_gain_measured']:.2f})" if "fresh_gain_measured" in final else "") + ".")
    lines += [f"This run cannot show {blind['effect']}: {blind['reason']}; {blind['hint']}." for blind in untestable]
    return "\n".join(lines)


def _fresh_lines(s: Candidate) -> list[str]:
    """What the step promises a fresh run (and, when one was given, what it did there)."""
    lines = []
    if (e := s.fresh_expected) is not None:
        lines.append(
            f"  On a fresh run of the same kind expect about {_nm(e.rms_before_um, e.rms_after_um)} (RMS × "
            f"{e.ratio:.2f}), not the held-out figures: held-out blocks share this run's room history and slow "
            "interferometer wander, so the estimate adds back what fitting hides of them"
            + (" (with the drift's source fixed or sensed)" if s.fresh_if_source_remains is not None else "") + ".")
    if (r := s.fresh_if_source_remains) is not None:
        lines.append(f"  While the drift's source remains, a fresh run is worse with the written model: about "
                     f"{_nm(r.rms_before_um, r.rms_after_um)} (× {r.ratio:.2f}).")
    if (m := s.fresh_measured) is not None:
        lines.append(f"  Measured on the fresh run given: {_nm(m.rms_before_um, m.rms_after_um)} (× {m.ratio:.2f}).")
    return lines


def _nm(before_um: float, after_um: float) -> str:
    return f"{before_um * 1000:.1f} → {after_um * 1000:.1f} nm"
