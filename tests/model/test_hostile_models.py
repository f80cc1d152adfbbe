"""Hostile model files fail cleanly: a ModelFileError naming the file, never a traceback.

Reproductions 5 and 6 of issue 10: '['*100000 nested JSON raised RecursionError in check-config,
predict and run; x^400, x^999999 and a coefficient of 1e308 loaded, and predict wrote inf into
q_pred_um. Issue 16: a FIFO or /dev/zero as the model path blocked the daemon or filled its memory.
Property-based: any mutation of a valid file either loads as a model whose prediction is
finite over its training box, or is refused by a message that starts with the file's path.
"""

from __future__ import annotations

import json
import math
import os
import resource
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.budget import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import nanodrift.model.model as model_module
from nanodrift.calibration.dataset import Dataset, read_csv, write_csv
from nanodrift.cli import main
from nanodrift.model.model import MAX_MODEL_BYTES, FittedTerm, Model, ModelFileError, Training, load_model, save_model
from nanodrift.model.terms import MAX_POWER, parse_term

REPO = Path(__file__).resolve().parents[2]
NESTED = "[" * 100_000 + "]" * 100_000


def good_doc() -> dict[str, Any]:
    model = Model(
        terms=[FittedTerm(parse_term(n), c, se=0.01, p=0.01) for n, c in
               {"x^3": 2e-8, "x": 1.0, "T1": -0.5, "lag(T2, 300 s)": 0.2, "dir": 0.01, "1": 3.0}.items()],
        training=Training((0.0, 480.0), {"T1": (21.0, 22.0), "T2": (20.5, 22.5)}, 50, 600.0),
    )
    model.id = model.content_id()
    return model.to_dict()


def write(path: Path, doc: Any, restamp: bool = True) -> Path:
    """The file, stamped with its content's id when it parses as a model (so other checks are reached)."""
    if restamp and isinstance(doc, dict):
        try:
            doc = dict(doc, id=Model.from_dict(doc, "m", check_id=False).content_id())
        except ModelFileError:
            pass
    path.write_text(json.dumps(doc))
    return path


def refused(path: Path, fragment: str) -> str:
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and fragment in message, message
    return message


def test_deeply_nested_json_is_a_model_file_error_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "nested.json"
    path.write_text(NESTED)
    refused(path, "nested too deeply")
    doc = good_doc()
    doc["provenance"]["note"] = json.loads("[" * 40 + "]" * 40)  # parses, but deeper than any model file
    refused(write(tmp_path / "deep.json", doc, restamp=False), "nested too deeply")


@pytest.mark.parametrize("power", [13, 400, 999_999, 10**30])
def test_the_power_of_x_is_bounded(tmp_path: Path, power: int) -> None:
    doc = good_doc()
    doc["terms"][0]["term"] = f"x^{power}"
    refused(write(tmp_path / "m.json", doc), f"terms[0]: power of x must be between 1 and {MAX_POWER}")


def test_x_to_the_12_is_still_a_model(tmp_path: Path) -> None:
    doc = good_doc()
    doc["terms"][0].update(term="x^12", coef=1e-30)
    assert load_model(write(tmp_path / "m.json", doc)).terms[0].term.name == "x^12"


@pytest.mark.parametrize(
    ("field", "literal", "fragment"),
    [
        ("coef", "1e400", "'coef' must be a finite number, got inf"),
        ("coef", "NaN", "'coef' must be a finite number, got nan"),
        ("coef", "-Infinity", "'coef' must be a finite number, got -inf"),
        ("se", "Infinity", "'se' must be a finite number >= 0 or null, got inf"),
        ("se", "-0.5", "'se' must be a finite number >= 0 or null"),
        ("se", '"0.1"', "'se' must be a finite number >= 0 or null"),
        ("p", "1.5", "'p' must be a finite number within [0, 1] or null"),
        ("coef", "9" * 5000, "not valid JSON"),  # more digits than Python converts to an int
    ],
)
def test_non_finite_or_malformed_numbers_are_refused(tmp_path: Path, field: str, literal: str,
                                                     fragment: str) -> None:
    doc = good_doc()
    doc["terms"][1][field] = "@@"
    path = tmp_path / "m.json"
    path.write_text(json.dumps(doc).replace('"@@"', literal))
    message = refused(path, fragment)
    assert "x" in message


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"coef": 1e308}, "term x^3 (coef 1e+308) is not finite inside the training box (x_um 0..480)"),
        ({"term": "x^12", "coef": 1e280}, "term x^12 (coef 1e+280) is not finite inside the training box"),
    ],
)
def test_a_model_that_overflows_inside_its_training_box_is_refused(tmp_path: Path, changes: dict[str, Any],
                                                                   fragment: str) -> None:
    doc = good_doc()
    doc["terms"][0].update(changes)
    refused(write(tmp_path / "m.json", doc), fragment)


def test_terms_that_overflow_only_together_are_refused(tmp_path: Path) -> None:
    doc = good_doc()
    doc["terms"][1]["coef"] = 3e305  # x: 480 * 3e305 = 1.44e308 is finite alone ...
    doc["terms"][5]["coef"] = 1.7e308  # ... and with the bias the sum is not
    refused(write(tmp_path / "m.json", doc), "the sum of the terms overflows inside the training box")


@pytest.mark.parametrize("name", ["lag(T2, 1e400 s)", "dir(1e999 um)", "rate(T2, 1e400 s)", "creep(1e400 s)"])
def test_non_finite_numbers_in_term_names_are_refused(tmp_path: Path, name: str) -> None:
    doc = good_doc()
    doc["terms"][3]["term"] = name
    refused(write(tmp_path / "m.json", doc), "must be a finite number")


# --- the commands ----------------------------------------------------------------------------


def data_file(path: Path, x: list[float]) -> Path:
    n = len(x)
    write_csv(Dataset(t=np.arange(n, dtype=float), x=np.asarray(x, dtype=float), q=np.asarray(x, dtype=float),
                      channels={"T1": np.full(n, 21.5), "T2": np.full(n, 21.0)}), path)
    return path


def test_predict_with_a_hostile_model_says_so_without_a_traceback(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    nested = tmp_path / "nested.json"
    nested.write_text(NESTED)
    data = data_file(tmp_path / "d.csv", [0.0, 240.0, 480.0])
    assert main(["predict", "--model", str(nested), str(data), "--out", str(tmp_path / "p.csv")]) == 2
    err = capsys.readouterr().err
    assert f"nanodrift predict: error: {nested}: not a model file" in err and "Recursion" not in err
    assert not (tmp_path / "p.csv").exists()


def test_a_model_file_naming_a_key_twice_is_refused_naming_the_key(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Stamped for its last ``coef`` (what json.loads keeps), with an earlier one the eye reads first."""
    doc = good_doc()
    doc["terms"][0]["coef"] = 9.0
    path = write(tmp_path / "m.json", doc)
    text = path.read_text()
    path.write_text(text.replace('"coef": 9.0', '"coef": 2e-08, "coef": 9.0', 1))
    data = data_file(tmp_path / "d.csv", [0.0, 240.0, 480.0])
    assert main(["predict", "--model", str(path), str(data), "--out", str(tmp_path / "p.csv")]) == 2
    err = capsys.readouterr().err
    assert f"{path}: not a model file: key 'coef' appears twice in one object" in err, err
    assert not (tmp_path / "p.csv").exists()


def test_predict_never_writes_a_non_finite_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "m.json"
    save_model(Model.from_dict(good_doc(), "m"), path)
    data = data_file(tmp_path / "d.csv", [0.0, 240.0, 1e103, 480.0, 1e200])  # x^3 of 1e103 overflows
    out = tmp_path / "p.csv"
    assert main(["predict", "--model", str(path), str(data), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{data}, row 4: the model gives no finite command for x_um = 1e+103" in err
    assert "(2 such row(s)" in err and not out.exists()
    ok = data_file(tmp_path / "ok.csv", [0.0, 240.0, 480.0])
    assert main(["predict", "--model", str(path), str(ok), "--out", str(out)]) == 0
    assert np.isfinite(read_csv(out).extra["q_pred_um"]).all()


def test_check_config_with_a_nested_model_names_the_file(tmp_path: Path) -> None:
    nested = tmp_path / "nested.json"
    nested.write_text(NESTED)
    config = tmp_path / "cell.toml"
    config.write_text(f'cell = "c"\n[model]\npath = "{nested}"\n')
    result = subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", str(config)], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    output = result.stdout + result.stderr
    assert "Traceback" not in output and "RecursionError" not in output, output
    assert f"{nested}: not a model file" in output, output


# --- property-based --------------------------------------------------------------------------

LEAVES = st.one_of(
    st.none(), st.booleans(), st.integers(-(10**20), 10**20), st.text(max_size=12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e308, -1e308, 5e-324, "x^999999", "lag(T1, 1e400 s)", "T9", "1", "dir", [], {}, [1, 2, 3]]),
)
JSON = st.recursive(LEAVES, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                    st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                    max_leaves=12)


def paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += paths(v, (*prefix, i))
    return out


def replaced(doc: Any, where: tuple[Any, ...], value: Any) -> Any:
    if not where:
        return value
    copy = json.loads(json.dumps(doc))
    node = copy
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    return copy


@settings(max_examples=examples(250), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), restamp=st.booleans())
def test_any_mutated_model_file_loads_finite_or_is_refused_naming_the_file(tmp_path: Path, data: st.DataObject,
                                                                            restamp: bool) -> None:
    doc = good_doc()
    where = data.draw(st.sampled_from(paths(doc)))
    mutated = replaced(doc, where, data.draw(JSON))
    path = tmp_path / "mutated.json"
    if restamp and isinstance(mutated, dict):
        try:
            mutated = dict(mutated, id=Model.from_dict(mutated, "m", check_id=False).content_id())
        except ModelFileError:
            pass
    path.write_text(json.dumps(mutated, allow_nan=True))
    try:
        model = load_model(path)
    except ModelFileError as err:
        assert str(err).startswith(f"{path}: "), err
        return
    corners = Dataset(t=np.arange(2.0), x=np.asarray(model.training.x_range),
                      channels={c: np.asarray(model.training.channel_ranges[c]) for c in model.channels})
    assert all(math.isfinite(q) for q in model.predict(corners))


@settings(max_examples=examples(150), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.one_of(st.text(max_size=200), st.binary(max_size=200).map(lambda b: b.decode("latin-1")),
                      JSON.map(json.dumps)))
def test_any_text_is_a_model_or_a_message_naming_the_file(tmp_path: Path, text: str) -> None:
    path = tmp_path / "any.json"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    try:
        load_model(path)
    except ModelFileError as err:
        assert str(err).startswith(f"{path}: "), err


# --- issue 16 (problem 11): the model path must be a regular file of bounded size ------------------

LOAD = """
import sys
from nanodrift.model.model import ModelFileError, load_model
try:
    load_model(sys.argv[1])
except ModelFileError as err:
    print(err)
"""


def load_in_a_process(path: Path) -> subprocess.CompletedProcess[str]:
    """``load_model(path)`` in its own process, capped at 1 GiB and 30 s: a regression that blocks on a
    FIFO or reads /dev/zero fails the test instead of hanging the suite or filling the machine's memory."""
    def cap_memory() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (2**30, 2**30))

    return subprocess.run([sys.executable, "-c", LOAD, str(path)], capture_output=True, text=True, cwd=REPO,
                          timeout=30, preexec_fn=cap_memory)


@pytest.mark.parametrize("kind", ["fifo", "dev-zero"])
def test_a_fifo_or_a_device_is_refused_before_it_is_read(tmp_path: Path, kind: str) -> None:
    if kind == "fifo":
        path, what = tmp_path / "model.json", "a FIFO (named pipe)"
        os.mkfifo(path)  # no writer: opening it for reading would block for ever
    else:
        path, what = Path("/dev/zero"), "a character device"
    result = load_in_a_process(path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"{path}: {what}, not a model file: expected a regular file " \
                                    "(nanodrift-model/1 JSON)", result.stdout + result.stderr


def test_a_file_larger_than_the_bound_is_refused_unread(tmp_path: Path) -> None:
    path = tmp_path / "model.json"
    with path.open("wb") as file:
        file.truncate(MAX_MODEL_BYTES + 1)  # sparse: no disk used; zeros that would parse as no JSON
    refused(path, f"{MAX_MODEL_BYTES + 1} bytes, larger than 64 MiB: not a model file")


def test_a_fifo_swapped_in_after_the_check_does_not_block(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The stat says regular file, the open finds a FIFO (renamed in between): refused, not blocked."""
    fifo = tmp_path / "model.json"
    os.mkfifo(fifo)
    regular = os.stat(write(tmp_path / "good.json", good_doc()))
    real_stat = os.stat
    monkeypatch.setattr(model_module.os, "stat", lambda p, *a, **k: regular if Path(p) == fifo else real_stat(p))
    result: list[BaseException | None] = []
    worker = threading.Thread(target=lambda: result.append(_load_error(fifo)), daemon=True)
    worker.start()
    worker.join(10)
    if worker.is_alive():  # release the blocked open so the thread ends, then fail
        with open(fifo, "wb"):
            pass
        pytest.fail("load_model blocked on a FIFO")
    assert isinstance(result[0], ModelFileError), result
    assert str(result[0]) == f"{fifo}: a FIFO (named pipe), not a model file: expected a regular file " \
                             "(nanodrift-model/1 JSON)"


def _load_error(path: Path) -> BaseException | None:
    try:
        load_model(path)
    except BaseException as err:  # the test inspects whatever it was
        return err
    return None
