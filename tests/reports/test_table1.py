"""Table I as people write it: ratios as "4.0×", empty cells as "—" (issue 13, item 6)."""

from helpers.benchmark_module import load_benchmark

from nanodrift.calibration.iso9283 import summarize
from nanodrift.calibration.plans import PlannedStep, StepResult
from nanodrift.reports.validation import PAPER_TABLE1, table1


def a_test(name: str, compensated: bool, error_um: float, drift_um: float):
    """Every visit of 0 and 80 µm lands ``error_um`` off; the commands made up for ``drift_um``."""
    steps = []
    for i in range(8):
        target = 80.0 * (i % 2)
        q = target - drift_um if compensated else target
        steps.append(StepResult(PlannedStep.on_x(i, i // 2, target), float(i), q_um={"x": q},
                                positions_um={"x": target + error_um},
                                temperatures={"T1": 22.0}, valid=True))
    return summarize(name, steps, compensated=compensated)


def test_ratios_and_empty_cells_read_as_in_the_paper():
    test1 = a_test("test1", False, 0.4, 0.0)
    test2 = a_test("test2", True, 0.1, 0.3)  # without: 0.1 + 0.3 = 0.4 um, with: 0.1 um -> 4.0×
    text = table1([test1, test2], paper=PAPER_TABLE1)
    row1 = next(line for line in text.splitlines() if line.startswith("test1"))
    row2 = next(line for line in text.splitlines() if line.startswith("test2"))
    assert "400 nm*" in row2 and "100 nm" in row2 and "4.0×" in row2
    assert "10.8×" in row2  # the paper: 378 / 35
    assert "x (" not in text and "%" not in text
    assert "\\" not in text
    assert row1.count("—") == 4  # with comp. and improvement, ours and the paper's


def _benchmark():
    return load_benchmark("paper_table1")


def test_table_one_over_seeds_is_drawn_with_its_interval_and_footer(tmp_path):
    """Issue 27: fig. 11 over seeds (the benchmark's): medians with their 5th-95th percentile as error bars."""
    bench = _benchmark()
    runs = [{"tests": {t: {"ap_without": 400.0 + seed, "ap_with": 40.0 + 2 * seed} for t in bench.TESTS}}
            for seed in range(16)]
    files = bench.figure_over_seeds(runs, tmp_path, "python benchmarks/paper_table1.py --seeds 16")
    assert [f.name for f in files] == ["fig11_accuracy_over_seeds.png", "fig11_accuracy_over_seeds.svg"]
    svg = files[1].read_text()
    assert 'id="interval-ap_with' in svg and 'id="interval-ap_without' in svg
    assert "python benchmarks/paper_table1.py --seeds 16" in svg and "40 nm" in svg
    assert bench.spread([40.0 + 2 * s for s in range(16)]) == "55 [42, 68]"  # median [5th, 95th], interpolated
