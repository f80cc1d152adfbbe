"""Table I as people write it: ratios as "4.0×", empty cells as "—" (issue 13, item 6)."""

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
