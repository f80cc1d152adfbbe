"""A facility (issue 29): simulated cells (20 with NANODRIFT_LONG_TESTS=1, as ``benchmarks/fleet.py``; 6 by
default, each group's rule the same) behind one Zenoh router under the prefix ``site/hall2``,
with user/password authentication and the access control ``nanodrift acl`` writes.

Group ``a`` (alice) may move the first half of the cells, group ``b`` (bob) the second half, group ``watch``
(grafana) none; every one of them may read every cell. Each "cannot" is checked where it matters:
the daemon of the cell that must not move counts no target (its status, asked by the router's own
session), after a sentinel target of the same client to one of its own cells has been answered (the
client's messages go through the router in order, so a target the ACL had let through would have
arrived first). A control shows that bob does move his cell, so the refusals are the ACL's.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from helpers.budget import LONG_TESTS
from helpers.daemon_harness import REPO, run_cli
from helpers.fleet import PREFIX, Fleet, cell_name

from nanodrift import Client
from nanodrift.client import client_config

CELLS = 20 if LONG_TESTS else 6
GROUPS = {"a": (["alice"], [cell_name(i) for i in range(CELLS // 2)]),
          "b": (["bob"], [cell_name(i) for i in range(CELLS // 2, CELLS)]),
          "watch": (["grafana"], [])}
#: seconds a refused move waits for an answer that must not come
REFUSED_WAIT_S = 1.5
A_FIRST, A_LAST = cell_name(0), cell_name(CELLS // 2 - 1)  # alice's
B_CELL, B_LAST = cell_name(CELLS - 2), cell_name(CELLS - 1)  # bob's


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    started = Fleet(tmp_path_factory.mktemp("fleet"), CELLS, groups=GROUPS).start()
    yield started
    codes = started.close()
    assert set(codes.values()) == {0}, codes


def nanodrift(*args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift ARGS`` run by the console script's own ``main`` in this process (``status`` only talks to the
    site's router: a process of its own would add half a second of CPU start-up and test nothing more here)."""
    return run_cli(*args, cwd=REPO)


def targets_counted(fleet: Fleet, cell: str) -> int:
    counters = fleet.status_of(cell)["counters"]
    assert isinstance(counters, dict)
    return int(counters["targets"])


def test_status_lists_every_cell_of_the_site_within_2_s(fleet: Fleet) -> None:
    result = nanodrift("status", "--prefix", PREFIX, "-e", fleet.endpoint, "--zenoh-config",
                       str(fleet.user_configs["grafana"]), "--json", "--timeout", "2")
    assert result.returncode == 0, result.stderr
    docs = json.loads(result.stdout)
    assert [doc["cell"] for doc in docs] == [cell_name(i) for i in range(CELLS)]
    assert all(doc["model"]["id"] == docs[0]["model"]["id"] for doc in docs)
    table = nanodrift("status", "--prefix", PREFIX, "-e", fleet.endpoint, "--zenoh-config",
                      str(fleet.user_configs["alice"]), "--timeout", "2")
    assert table.returncode == 0 and f"({CELLS} cells" in table.stdout, table.stdout + table.stderr


def test_a_group_moves_its_own_cells_and_not_the_other_groups(fleet: Fleet) -> None:
    before = targets_counted(fleet, B_CELL)
    with Client(fleet.endpoint, B_CELL, prefix=PREFIX, zenoh_config=fleet.user_configs["alice"]) as foreign:
        with pytest.raises(TimeoutError):
            foreign.move(100.0, timeout_s=REFUSED_WAIT_S)
        with pytest.raises(TimeoutError):
            foreign.stop()  # stop is a target-like right too: only b may stop b's cells
    with Client(fleet.endpoint, A_LAST, prefix=PREFIX, zenoh_config=fleet.user_configs["alice"]) as own:
        command = own.move(120.0)  # the sentinel: alice's own cell answers
        assert command.model is not None and command.target == pytest.approx(120.0, abs=1e-9)
    assert targets_counted(fleet, B_CELL) == before  # the daemon of b's cell never saw alice's target
    with Client(fleet.endpoint, B_CELL, prefix=PREFIX, zenoh_config=fleet.user_configs["bob"]) as owner:
        assert owner.move(140.0).target == pytest.approx(140.0, abs=1e-9)  # control: the owner does move it
    assert targets_counted(fleet, B_CELL) == before + 1


def test_a_wildcard_put_reaches_no_cell(fleet: Fleet) -> None:
    """A put on ``site/hall2/*/target`` would move every cell: no rule includes it, so no cell hears it."""
    before = {cell: targets_counted(fleet, cell) for cell in (A_FIRST, B_LAST)}
    session = zenoh.open(client_config(fleet.endpoint, zenoh_config=fleet.user_configs["alice"]))
    try:
        session.put(f"{PREFIX}/*/target", json.dumps({"x_um": 50.0, "id": "everyone"}))
        session.put(f"{PREFIX}/**", json.dumps({"x_um": 50.0, "id": "everything"}))
        replies = list(session.get(f"{PREFIX}/{A_FIRST}/compensate", payload=json.dumps({"x_um": 60.0, "id": "s"}),
                                   timeout=10.0))  # the sentinel, same session
        assert [r.ok is not None for r in replies] == [True]
    finally:
        session.close()
    assert targets_counted(fleet, A_FIRST) == before[A_FIRST] + 1  # the sentinel only
    assert targets_counted(fleet, B_LAST) == before[B_LAST]


def test_a_watching_group_reads_every_cell_and_moves_none(fleet: Fleet) -> None:
    before = targets_counted(fleet, A_FIRST)
    with Client(fleet.endpoint, A_FIRST, prefix=PREFIX, zenoh_config=fleet.user_configs["grafana"]) as watcher:
        assert watcher.status()["cell"] == A_FIRST
        with pytest.raises(TimeoutError):
            watcher.move(100.0, timeout_s=REFUSED_WAIT_S)
        assert len(watcher.statuses(timeout_s=2.0)) == CELLS
    with Client(fleet.endpoint, A_FIRST, prefix=PREFIX, zenoh_config=fleet.user_configs["alice"]) as own:
        own.move(110.0)  # sentinel through the router
    assert targets_counted(fleet, A_FIRST) == before + 1


def test_an_unknown_user_gets_no_session(fleet: Fleet, tmp_path: Path) -> None:
    from helpers.fleet import credentials_config

    stranger = credentials_config(tmp_path / "stranger.json5", "mallory", "guess")
    result = nanodrift("status", "--prefix", PREFIX, "-e", fleet.endpoint, "--zenoh-config", str(stranger))
    assert result.returncode != 0 and "cannot open a zenoh session" in result.stderr
