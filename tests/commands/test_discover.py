"""``nanodrift discover`` (issue 13, item 7): nothing found means no model, a hint when the run cannot show
an effect (forward-only sweeps and hysteresis), and the extended model records the running version."""

from __future__ import annotations

import importlib.metadata
import json
from pathlib import Path

from helpers.discovery_helpers import cell_run, paper_model

from nanodrift.calibration.dataset import write_csv
from nanodrift.cli import main
from nanodrift.model.model import load_model, save_model

SOFTWARE = f"nanodrift {importlib.metadata.version('nanodrift')}"
HINTS = ("nanodrift simulate --scenario bidirectional",
         'nanodrift calibrate` with `[procedure] trajectory = "bidirectional"` on the stage')


#: the files :func:`recorded` wrote for each (effects, seed, bidirectional), as bytes: a run simulated and fitted
#: once per module, and its files written afresh into each test's own directory (tests edit theirs)
_RECORDED: dict[tuple[str, int, bool], tuple[bytes, bytes]] = {}


def recorded(tmp_path: Path, effects: str, seed: int, bidirectional: bool = False) -> tuple[Path, Path]:
    csv, model = tmp_path / "d.csv", tmp_path / "m.json"
    key = (effects, seed, bidirectional)
    if key in _RECORDED:
        csv.write_bytes(_RECORDED[key][0])
        model.write_bytes(_RECORDED[key][1])
        return csv, model
    data = cell_run(effects, seed=seed, bidirectional=bidirectional)
    write_csv(data, csv)
    save_model(paper_model(data), model)
    assert str(tmp_path) not in csv.read_text() + model.read_text()  # nothing of this test's own in them
    _RECORDED[key] = (csv.read_bytes(), model.read_bytes())
    return csv, model


def test_nothing_found_writes_no_model_and_says_so(tmp_path, capsys) -> None:
    data, model = recorded(tmp_path, "", seed=0)
    out = tmp_path / "m2.json"
    assert main(["discover", str(data), "--model", str(model), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "nothing found; no model written" in text
    assert "extended model" not in text
    assert not out.exists()

    assert main(["discover", str(data), "--model", str(model), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["steps"] == [] and doc["model_out"] is None
    assert doc["final"]["model"] == load_model(model).id  # the given model stands: no new id
    assert not out.exists()


def test_a_forward_only_run_says_it_cannot_show_hysteresis_and_how_to_record_one_that_can(tmp_path, capsys) -> None:
    data, model = recorded(tmp_path, "hysteresis", seed=0)
    assert main(["discover", str(data), "--model", str(model), "--out", str(tmp_path / "m2.json")]) == 0
    text = capsys.readouterr().out
    assert "cannot show hysteresis" in text and "forward-only" in text
    assert all(hint in text for hint in HINTS), text
    assert main(["discover", str(data), "--model", str(model), "--out", str(tmp_path / "m3.json"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [u["effect"] for u in doc["final"]["untestable"]] == ["hysteresis"]
    assert "hysteresis" not in [s["effect"] for s in doc["steps"]]


def test_the_hinted_bidirectional_run_shows_the_hysteresis(tmp_path, capsys) -> None:
    """Follow the hint: simulate the bidirectional scenario, fit, discover: hysteresis is named, no hint."""
    data, model, out = tmp_path / "bi.csv", tmp_path / "m.json", tmp_path / "m2.json"
    assert main(["simulate", "--scenario", "bidirectional", "--effects", "hysteresis", "--cycles", "12",
                 "--seed", "1", "--out", str(data)]) == 0
    assert main(["fit", str(data), "--out", str(model)]) == 0
    capsys.readouterr()
    assert main(["discover", str(data), "--model", str(model), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [s["effect"] for s in doc["steps"]][:1] == ["hysteresis"], doc["final"]["summary"]
    assert doc["final"]["untestable"] == [] and doc["model_out"] == str(out)
    assert "dir" in load_model(out).term_names()


def test_the_extended_model_records_the_running_version(tmp_path, capsys) -> None:
    data, model = recorded(tmp_path, "creep:c=0.01,tau_s=15", seed=7)
    doc = json.loads(model.read_text())
    doc["provenance"]["software"] = "nanodrift 0.0.1"  # fitted by an older nanodrift
    model.write_text(json.dumps(doc))
    out = tmp_path / "m2.json"
    assert main(["discover", str(data), "--model", str(model), "--out", str(out)]) == 0
    capsys.readouterr()
    extended = load_model(out)
    assert extended.provenance["software"] == SOFTWARE
    assert extended.provenance["base_model"] == load_model(model).id


def test_the_reports_figures_name_the_model_and_the_data_they_came_from(tmp_path, capsys) -> None:
    """Issue 19, item 7: every figure carries a footer with the model id and the data file it was run on."""
    data, model = recorded(tmp_path, "", seed=0)
    report = tmp_path / "report"
    assert main(["discover", str(data), "--model", str(model), "--out", str(tmp_path / "m2.json"),
                 "--report", str(report)]) == 0
    svgs = sorted(report.glob("*.svg"))
    assert svgs
    for svg in svgs:
        text = svg.read_text()
        assert load_model(model).id in text and f"discovered on {data}" in text, svg.name
