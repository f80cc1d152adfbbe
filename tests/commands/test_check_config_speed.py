"""``check-config`` on a fast simulated clock (issue 19.6): sensor timing the daemon cannot serve at
``[simulation] speed`` is a warning naming the sensor, the key and what would do; the default sensors
(no ``[[sensors]]``) are scaled to the speed and draw none of those; their position poll (20 s of cell time at
10000x) is slower than ``[health] window_s``, which is the one warning left (issue 26.9: no hold is recorded)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.daemon_harness import write_test_model

from nanodrift.cli import main


def check(capsys: pytest.CaptureFixture[str], path: Path) -> tuple[int, str]:
    code = main(["check-config", str(path)])
    return code, capsys.readouterr().err


def test_sensors_too_fast_for_the_speed_are_a_warning_naming_sensor_key_and_limit(tmp_path: Path, capsys) -> None:
    write_test_model(tmp_path / "model.json")
    path = tmp_path / "fast.toml"
    path.write_text('[model]\npath = "model.json"\n[simulation]\nspeed = 10000.0\n'
                    '[[sensors]]\nname = "T1"\nkind = "simulated"\ninterval_s = 0.5\nmax_age_s = 5.0\n'
                    '[[sensors]]\nname = "T2"\nkind = "simulated"\ninterval_s = 20.0\nmax_age_s = 1000.0\n')
    code, err = check(capsys, path)
    assert code == 0
    assert "warning: sensors[0] (T1).max_age_s: 5 s of cell time is 0.5 ms of wall time at simulation.speed 10000" \
        in err
    assert "make it at least 1000 s or lower the speed to 50" in err
    assert "warning: sensors[0] (T1).interval_s:" in err
    assert "(T2)" not in err
    path.write_text('[model]\npath = "model.json"\n[simulation]\nspeed = 10000.0\n')
    code, err = check(capsys, path)
    assert code == 0 and "max_age_s" not in err
    assert [line for line in err.splitlines() if "interval_s" in line] == [
        f"{path}: warning: sensors[4] (interferometer).interval_s: polls every 20 s, not faster than [health] "
        "window_s = 2 s: a held target whose window no reading falls into gets no residual and no record row "
        "(counted as holds_unrecorded); make window_s larger than 20 s or poll faster"]
