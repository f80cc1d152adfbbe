"""The CSV writer formats a column at a time (a season's million rows in seconds): the text is what the
row-by-row formatter wrote."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nanodrift.calibration.dataset import Dataset, write_csv


def test_the_csv_writer_formats_every_cell_as_the_row_formatter_did(tmp_path: Path) -> None:
    """Floats ``repr``-exact, ``cycle`` and ``valid`` as whole numbers, across chunk boundaries."""
    rng = np.random.default_rng(5)
    n = 120_001  # three chunks of the writer
    data = Dataset(t=np.arange(n) * 0.1, x=rng.normal(size=n) * 1e3, q=rng.normal(size=n) / 7.0,
                   channels={"T1": 20.0 + rng.normal(size=n) * 1e-9},
                   extra={"cycle": np.repeat(np.arange(3.0), 40_001)[:n], "valid": (rng.random(n) > 0.1) * 1.0})
    write_csv(data, tmp_path / "d.csv")
    lines = (tmp_path / "d.csv").read_text().splitlines()
    columns = data.columns()
    assert lines[0] == ",".join(columns)
    row_format = ",".join("%d" if name in ("cycle", "valid") else "%r" for name in columns)
    expected = [row_format % row for row in zip(*(v.tolist() for v in columns.values()), strict=True)]
    assert lines[1:] == expected
