"""Several runs fitted together keep their own time: stateful terms restart, held-out blocks stay in one run."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.synthetic import TRUE_TERMS, paper_run

from nanodrift.calibration.dataset import DataError, Dataset, concat
from nanodrift.model.effect_terms import Creep, Rate
from nanodrift.model.identify import fit, holdout_blocks
from nanodrift.model.segments import features, run_time_s, spans_s
from nanodrift.model.terms import Direction, Lag, Term


def two_runs() -> tuple[Dataset, Dataset, Dataset]:
    """Two calibrations of the same cell, each with t_s from 0; the second 1.5 °C warmer (q follows)."""
    a, b = paper_run(cycles=5, seed=1), paper_run(cycles=3, seed=2)
    b.channels = {c: v + 1.5 for c, v in b.channels.items()}
    b.q = b.q + 1.5 * sum(coef for name, coef in TRUE_TERMS.items() if name.startswith("T"))
    return a, b, concat([a, b])


@pytest.mark.parametrize("term", [Lag("T1", 900.0), Rate("T2", 300.0), Direction(), Creep(20.0)],
                         ids=lambda t: t.name)
def test_stateful_terms_restart_at_each_run(term: Term) -> None:
    a, b, _ = two_runs()
    a.x = a.x[::-1].copy()  # run a ends moving down, run b starts moving up: dir and creep must restart
    both = concat([a, b])
    expected = np.concatenate([term.batch(a.t, a.x, a.channels), term.batch(b.t, b.x, b.channels)])
    np.testing.assert_array_equal(features(term, both), expected)
    # what concatenating the rows as one series would give instead (run b's time starts again at 0)
    joined = term.batch(both.t, both.x, both.channels)
    assert not np.allclose(joined[len(a):len(a) + 3], expected[len(a):len(a) + 3])


def test_held_out_blocks_never_straddle_runs_and_every_run_has_its_own() -> None:
    both = two_runs()[2]
    folds = holdout_blocks(both)
    for k in np.unique(folds):
        assert np.unique(both.segment[folds == k]).size == 1, f"block {k} spans two runs"
    assert set(np.unique(both.segment)) == {0, 1}
    assert np.unique(folds[both.segment == 1]).size >= 1 and np.unique(folds[both.segment == 0]).size >= 3
    cycles = both.cycles()
    for c in np.unique(cycles):
        assert np.unique(folds[cycles == c]).size == 1, f"cycle {c} is split between blocks"


def test_cycles_of_several_runs_are_numbered_apart() -> None:
    a, _, both = two_runs()
    cycles = both.cycles()
    assert np.unique(cycles[: len(a)]).size == 5 and np.unique(cycles[len(a):]).size == 3
    assert cycles[: len(a)].max() < cycles[len(a):].min()


def test_time_is_measured_within_each_run() -> None:
    a, b, both = two_runs()
    assert spans_s(both) == [float(a.t[-1] - a.t[0]), float(b.t[-1] - b.t[0])]
    rt = run_time_s(both)
    assert rt[len(a)] == 0.0 and rt[-1] == b.t[-1] - b.t[0]


def test_two_runs_on_the_same_clock_fit_together_and_cover_both_temperature_ranges() -> None:
    """Two calibrations whose t_s both start at 0: one series would not even have increasing time."""
    a, b, both = two_runs()
    model = fit(both, order=3).model
    lo, hi = model.training.channel_ranges["T1"]
    assert lo == pytest.approx(min(a.channels["T1"].min(), b.channels["T1"].min()))
    assert hi == pytest.approx(max(a.channels["T1"].max(), b.channels["T1"].max()))
    assert model.training.rows == len(a) + len(b)
    assert model.training.t_span_s == pytest.approx(sum(spans_s(both)))
    alone = fit(a, order=3).model
    assert alone.training.channel_ranges["T1"][1] < hi - 1.0


def test_a_run_lacking_a_channel_is_named() -> None:
    a, b, _ = two_runs()
    b.channels.pop("T3")
    b.source = "records-2026-11-23.csv"
    with pytest.raises(DataError, match=r"records-2026-11-23\.csv: lacks channel\(s\) T3"):
        concat([a, b])
