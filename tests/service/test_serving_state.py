"""The serving state (config + model -> compensator, sensor table, health) is built by one function at start
and at every reload, so a model the daemon cannot serve is refused in the same words at both.

Real pieces: the daemon's :class:`Service` (not run: its ``__init__`` builds the serving state) and its
:class:`Reloader` reading an edited config file from disk; only the log is a recorder.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from helpers.cell_helpers import write_cell_model
from helpers.daemon_harness import write_test_model

from nanodrift.config import load_config
from nanodrift.service.runner import Service
from nanodrift.service.status import status_doc

XY_AXES = "".join(f'[[axes]]\nname = "{axis}"\n[axes.actuator]\nkind = "zenoh"\n' for axis in ("x", "y"))


class RecordedLog:
    def __init__(self) -> None:
        self.lines: list[tuple[str, dict[str, Any]]] = []

    def _line(self, event: str, **fields: Any) -> None:
        self.lines.append((event, fields))

    info = warning = error = debug = _line


def no_drivers(config: Any, context: Any) -> Any:
    raise AssertionError("the drivers are not rebuilt: the edit changes only the model")


def write_config(path: Path, model: Path, axes: str) -> Path:
    path.write_text(f'cell = "c1"\n[model]\npath = "{model}"\n\n{axes}')
    return path


def bad_model(kind: str, tmp_path: Path) -> Path:
    """A model file the cell (one axis, or XY for ``xy-cell-...``) cannot serve."""
    path = tmp_path / f"{kind}.json"
    if kind == "one-axis-cell-xy-model":
        write_cell_model(path, ("x", "y"))
    elif kind == "xy-cell-one-axis-model":
        write_test_model(path)
    elif kind in ("one-axis-cell-corrupt", "xy-cell-corrupt"):
        path.write_text('{"format": "nanodrift-model/1", "terms": [')
    else:
        assert kind in ("one-axis-cell-missing", "xy-cell-missing")
    return path


@pytest.mark.parametrize("kind", ["one-axis-cell-xy-model", "one-axis-cell-corrupt", "one-axis-cell-missing",
                                  "xy-cell-one-axis-model", "xy-cell-corrupt", "xy-cell-missing"])
def test_a_model_the_cell_cannot_serve_gives_the_same_reason_at_start_and_at_reload(tmp_path: Path,
                                                                                     kind: str) -> None:
    axes = XY_AXES if kind.startswith("xy-cell") else ""
    good = tmp_path / "good.json"
    if axes:
        write_cell_model(good, ("x", "y"))
    else:
        write_test_model(good)
    bad = bad_model(kind, tmp_path)

    # at start: the daemon serves without it, saying why in status (and in every no_model refusal)
    started = Service(load_config(write_config(tmp_path / "bad.toml", bad, axes)), build_drivers=no_drivers)
    at_start = status_doc(started.state, True)
    assert at_start["model"] is None and at_start["model_problem"], at_start
    reason = at_start["model_problem"]
    assert str(bad) in reason

    # at reload: a running cell whose config is edited to name it refuses the edit, in the same words
    config_path = write_config(tmp_path / "cell.toml", good, axes)
    running = Service(load_config(config_path), config_path=config_path, build_drivers=no_drivers)
    serving = running.state.model_id()
    assert serving is not None
    log = RecordedLog()
    running.reloader.log = log
    write_config(config_path, bad, axes)
    assert asyncio.run(running.reloader.reload()) is False
    [(event, fields)] = [line for line in log.lines if line[0].startswith("reload_")]
    assert event == "reload_refused" and fields["problems"] == [f"model.path: {reason}"], fields
    assert status_doc(running.state, True)["model"]["id"] == serving  # the good model keeps serving
