"""Human-readable output in µm and °C (issue 13, item 6): fit's training ranges, validate's per-point lines,
calibrate's summary. JSON keys keep their ASCII unit suffixes (``_um``, ``_nm``)."""

from __future__ import annotations

import json
import re

from helpers.synthetic import paper_run

from nanodrift.calibration.dataset import write_csv
from nanodrift.cli import main

ASCII_UNITS = re.compile(r"\bum\b|\bdegC\b")


def test_fit_prints_its_training_ranges_in_micrometres_and_degrees(tmp_path, capsys) -> None:
    data = tmp_path / "cal.csv"
    write_csv(paper_run(seed=3, cycles=6), data)
    assert main(["fit", str(data), "--out", str(tmp_path / "m.json"), "--order", "3"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^trained on x \d+\.\d\.\.\d+\.\d µm$", out, re.MULTILINE), out
    assert re.search(r"^  T1: [\d.]+\.\.[\d.]+ °C$", out, re.MULTILINE), out
    assert not ASCII_UNITS.search(out)
    assert main(["fit", str(data), "--out", str(tmp_path / "m.json"), "--order", "3", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "x_um" in doc["training"] and "residual_rms_nm" in doc  # keys unchanged


def test_calibrate_and_validate_print_micrometres_and_degrees(tmp_path, capsys) -> None:
    model = tmp_path / "m.json"
    assert main(["calibrate", "--out", str(model), "--cycles", "2"]) == 0
    printed = capsys.readouterr().out  # calibrate's result is on stdout (issue 19)
    assert re.search(r"^trained on x 0\.0\.\.\d+\.\d µm$", printed, re.MULTILINE), printed  # never "-0.0"
    assert " °C" in printed and not ASCII_UNITS.search(printed)
    assert main(["validate", "--model", str(model), "--cycles", "1"]) == 0
    out = capsys.readouterr().out
    points = re.findall(r"^  x' = +(\d+) µm: accuracy", out, re.MULTILINE)
    assert points == ["0", "80", "160", "240", "320", "400", "480"], out
    assert not ASCII_UNITS.search(out)
