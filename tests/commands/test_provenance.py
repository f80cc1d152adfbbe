"""Each model file records the software that wrote it; the model id ignores it (issue 13, item 4)."""

import importlib.metadata
import json

from helpers.synthetic import paper_run

from nanodrift.calibration.dataset import write_csv
from nanodrift.cli import main
from nanodrift.model.model import load_model

SOFTWARE = f"nanodrift {importlib.metadata.version('nanodrift')}"


def test_fit_records_the_version_outside_the_model_id(tmp_path, capsys):
    data, out = tmp_path / "cal.csv", tmp_path / "m.json"
    write_csv(paper_run(seed=3, cycles=6), data)
    assert main(["fit", str(data), "--out", str(out), "--order", "3"]) == 0
    capsys.readouterr()
    doc = json.loads(out.read_text())
    assert doc["provenance"]["software"] == SOFTWARE
    model = load_model(out)
    assert model.provenance["software"] == SOFTWARE

    doc["provenance"]["software"] = "nanodrift 99.0"  # another version, the same terms and coefficients
    other = tmp_path / "other.json"
    other.write_text(json.dumps(doc))
    assert load_model(other).content_id() == model.content_id() == model.id
