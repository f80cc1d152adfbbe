"""A model's identity is its content: the id is a hash of what decides the commands, checked on load.

Reproduction 2 of issue 10: a model edited to keep its id used to load (and a reload kept the old
evaluator, so the edit was never applied). Now such a file is refused until ``nanodrift restamp``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from helpers.budget import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nanodrift.cli import main
from nanodrift.model.model import FittedTerm, Model, ModelFileError, Training, load_model, save_model
from nanodrift.model.terms import parse_term

DATA_DIR = Path(__file__).resolve().parents[2] / "daemon" / "data"
TERMS = {"x^3": 2.0e-8, "x^2": -1.0e-5, "x": 1.002, "T1": -0.6, "lag(T2, 300 s)": -0.5, "1": 0.5}


def model_of(terms: dict[str, float] | None = None) -> Model:
    return Model(
        terms=[FittedTerm(parse_term(n), c, se=0.01, p=0.001) for n, c in (terms or TERMS).items()],
        training=Training((0.0, 480.0), {"T1": (21.5, 22.1), "T2": (21.6, 22.05)}, 100, 3600.0),
        fit={"rmse_um": 0.02}, selection={"method": "stepwise"}, provenance={"data_file": "cal.csv"},
    )


def saved(tmp_path: Path, name: str = "m.json") -> tuple[Path, dict[str, Any]]:
    path = tmp_path / name
    save_model(model_of(), path)
    return path, json.loads(path.read_text())


def edit(path: Path, change: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc, indent=2))
    return doc


CONTENT_EDITS = {
    "a coefficient": lambda d: d["terms"][2].update(coef=2.0),
    "a standard error": lambda d: d["terms"][0].update(se=1e-9),
    "a term's name": lambda d: d["terms"][4].update(term="lag(T2, 600 s)"),
    "the x training range": lambda d: d["training"].update(x_um=[0.0, 500.0]),
    "a channel's training range": lambda d: d["training"]["channels"].update(T1=[21.0, 22.1]),
    "a term dropped": lambda d: d.update(terms=d["terms"][:-1]),
    # no covariance block: fit.rmse_um is every command's σ (issue 26.9: 8.98 nm edited to 0.001 nm)
    "the served rmse of a model without covariance": lambda d: d["fit"].update(rmse_um=1e-6),
}


@pytest.mark.parametrize("what", list(CONTENT_EDITS))
def test_an_edit_that_keeps_the_id_is_refused_saying_how_to_fix_it(tmp_path: Path, what: str) -> None:
    path, original = saved(tmp_path)
    edit(path, CONTENT_EDITS[what])
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    message = str(info.value)
    assert message.startswith(f"{path}: its id {original['id']!r} does not match its content"), message
    assert f"nanodrift restamp {path}" in message


@pytest.mark.parametrize(
    "change",
    [
        lambda d: d["provenance"].update(note="checked by J. on Monday"),
        lambda d: d["fit"].update(r2=0.5),
        lambda d: d["selection"].update(method="by hand"),
        lambda d: d["terms"][0].update(p=0.5),
        lambda d: d.update(channels=d.pop("channels")),  # key order and layout
    ],
)
def test_descriptive_fields_are_not_part_of_the_id(tmp_path: Path, change: Callable[[dict[str, Any]], None]) -> None:
    path, original = saved(tmp_path)
    edit(path, change)
    assert load_model(path).id == original["id"]


def test_the_id_is_the_content_hash_and_save_stamps_it(tmp_path: Path) -> None:
    model = model_of()
    model.id = "m-000000000000"  # whatever the object says, the file gets the id of its content
    save_model(model, tmp_path / "m.json")
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["id"] == model.id == model_of().content_id()
    assert model_of({**TERMS, "x": 1.003}).content_id() != model.id
    assert load_model(tmp_path / "m.json").id == doc["id"]


def test_a_file_without_an_id_is_refused(tmp_path: Path) -> None:
    path, _ = saved(tmp_path)
    edit(path, lambda d: d.pop("id"))
    with pytest.raises(ModelFileError, match=r"has no 'id'.*nanodrift restamp"):
        load_model(path)


def test_restamp_gives_an_edited_file_its_new_id(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, original = saved(tmp_path)
    edit(path, CONTENT_EDITS["a coefficient"])
    assert main(["restamp", str(path)]) == 0
    model = load_model(path)
    assert model.id != original["id"] and model.coefs[2] == 2.0
    assert model.provenance["restamped_from"] == original["id"] and model.provenance["data_file"] == "cal.csv"
    assert f"{path}: id {original['id']} -> {model.id}" in capsys.readouterr().out
    before = path.read_bytes()
    assert main(["restamp", str(path)]) == 0  # already right: nothing written
    assert path.read_bytes() == before and "nothing written" in capsys.readouterr().out


def test_restamp_out_leaves_the_original_alone(tmp_path: Path) -> None:
    path, _ = saved(tmp_path)
    edited = edit(path, CONTENT_EDITS["a channel's training range"])
    out = tmp_path / "sub" / "m2.json"
    assert main(["restamp", str(path), "--out", str(out)]) == 0
    assert json.loads(path.read_text()) == edited  # untouched, still refused
    assert load_model(out).training.channel_ranges["T1"] == (21.0, 22.1)


@pytest.mark.parametrize("in_place", [False, True], ids=["out_is_a_link", "model_is_a_link"])
def test_restamp_writes_through_a_symlink_and_keeps_the_link(tmp_path: Path, in_place: bool) -> None:
    """A lab's ``model.json -> models/m-nov.json``: the file the link names gets the restamped model, the link
    stays (it used to be replaced by a regular file, the versioned file left stale)."""
    path, original = saved(tmp_path)
    edit(path, CONTENT_EDITS["a coefficient"])
    versions = tmp_path / "models"
    versions.mkdir()
    named = versions / "m-nov.json"
    link = tmp_path / "current.json"
    if in_place:
        named.write_bytes(path.read_bytes())
        link.symlink_to(Path("models") / "m-nov.json")
        assert main(["restamp", str(link)]) == 0
    else:
        named.write_text("{}")  # what --out will replace
        link.symlink_to(Path("models") / "m-nov.json")
        assert main(["restamp", str(path), "--out", str(link)]) == 0
    assert link.is_symlink() and link.readlink() == Path("models") / "m-nov.json"
    model = load_model(named)
    assert model.id != original["id"] and model.coefs[2] == 2.0
    assert [p.name for p in versions.iterdir()] == ["m-nov.json"]  # no temporary file left beside it


def test_restamp_refuses_a_file_that_is_wrong_in_another_way(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = saved(tmp_path)
    edit(path, lambda d: d["terms"].append({"term": "x^40", "coef": 1.0}))
    before = path.read_bytes()
    assert main(["restamp", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"nanodrift restamp: error: {path}: terms[6]: power of x must be between 1 and 12" in err
    assert path.read_bytes() == before


def test_the_shipped_default_model_carries_its_content_id() -> None:
    model = load_model(DATA_DIR / "default_model.json")
    assert model.id == model.content_id()


@settings(max_examples=examples(60), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    index=st.integers(0, len(TERMS) - 1),
    coef=st.floats(-10.0, 10.0, allow_nan=False),
    se=st.one_of(st.none(), st.floats(0.0, 1.0)),
    lo=st.floats(-50.0, 100.0, allow_nan=False),
)
def test_any_change_of_content_changes_the_id(tmp_path: Path, index: int, coef: float, se: float | None,
                                              lo: float) -> None:
    path, original = saved(tmp_path, "prop.json")

    def change(d: dict[str, Any]) -> None:
        d["terms"][index].update(coef=coef, se=se)
        d["training"]["x_um"] = [lo, 480.0]

    doc = edit(path, change)
    same = Model.from_dict(doc, "m", check_id=False).content_id() == original["id"]
    if same:  # the edit happened to change nothing that is hashed
        assert load_model(path).id == original["id"]
    else:
        with pytest.raises(ModelFileError, match="does not match its content"):
            load_model(path)
