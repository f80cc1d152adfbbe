"""``check-config`` warns when the position sensor cannot fill ``[health] window_s`` (issue 26.9): held targets
then get no residual and no record row, which the daemon only counts once it runs."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.daemon_harness import write_test_model

from nanodrift.cli import main


def position_config(tmp_path: Path, interval_s: float, window_s: float = 2.0) -> Path:
    write_test_model(tmp_path / "model.json")
    path = tmp_path / "nanodrift.toml"
    path.write_text(f'[model]\npath = "model.json"\n[health]\nwindow_s = {window_s}\n'
                    + "".join(f'[[sensors]]\nname = "{name}"\nkind = "simulated"\n' for name in ("T1", "T2"))
                    + f'[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "simulated"\n'
                      f"interval_s = {interval_s}\n")
    return path


def test_a_position_sensor_slower_than_the_window_is_a_warning_at_its_interval(tmp_path: Path, capsys) -> None:
    path = position_config(tmp_path, interval_s=5.0)
    assert main(["check-config", str(path)]) == 0
    err = capsys.readouterr().err
    line = path.read_text().splitlines().index("interval_s = 5.0") + 1
    assert (f"{path}:{line}: warning: sensors[2] (interferometer).interval_s: polls every 5 s, not faster than "
            "[health] window_s = 2 s") in err, err
    assert "no record row" in err and "holds_unrecorded" in err
    assert main(["check-config", str(path), "--strict"]) == 2
    assert "sensors[2] (interferometer).interval_s" in capsys.readouterr().err


@pytest.mark.parametrize(("interval_s", "window_s", "warned"), [(0.1, 2.0, False), (1.99, 2.0, False),
                                                                 (2.0, 2.0, True), (0.5, 0.2, True)])
def test_the_warning_is_for_a_poll_no_faster_than_the_window(tmp_path: Path, capsys, interval_s: float,
                                                              window_s: float, warned: bool) -> None:
    assert main(["check-config", str(position_config(tmp_path, interval_s, window_s))]) == 0
    assert ("(interferometer).interval_s: polls every" in capsys.readouterr().err) is warned
