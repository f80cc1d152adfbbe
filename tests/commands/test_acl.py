"""``nanodrift acl``: the access control block for cells and client groups (issue 29).

What it writes is read by zenoh itself (``zenoh.Config.from_json5``), for generated lists of cells and
groups: each group may put ``target``/``stop`` and query ``compensate``/``stop`` on exactly its cells,
each daemon may send only under its own cell. ``--into`` keeps the rest of the shipped secure config.
Bad arguments are refused naming the group, cell or user, and nothing is written. That a router
enforces it is ``tests/service/test_fleet.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.commands.acl import NAME, USER, Group, access_control, parse_group, render_block, replace_block
from nanodrift.errors import UserError

REPO = Path(__file__).resolve().parents[2]
SECURE = REPO / "config" / "zenoh-secure.json5"

names = st.from_regex(r"[a-z][a-z0-9_-]{0,7}", fullmatch=True)


def zenoh_reads(block_text: str) -> dict[str, Any]:
    """The block as zenoh parses it (inside a config document), back as a dict."""
    conf = zenoh.Config.from_json5("{\n" + block_text + "\n}")
    doc = json.loads(conf.get_json("access_control"))
    assert isinstance(doc, dict)
    return doc


def allowed(block: dict[str, Any], user: str, flow: str, message: str) -> set[str]:
    """The key expressions on which ``user`` may send ``message`` in ``flow``."""
    subjects = {s["id"] for s in block["subjects"] if user in s.get("usernames", [])}
    rule_ids = {r for p in block["policies"] if set(p["subjects"]) & subjects for r in p["rules"]}
    return {key for rule in block["rules"] if rule["id"] in rule_ids and flow in rule["flows"]
            and message in rule["messages"] for key in rule["key_exprs"]}


@st.composite
def facilities(draw: st.DrawFn) -> tuple[list[str], list[Group], str]:
    cells = draw(st.lists(names, min_size=1, max_size=6, unique=True))
    group_names = draw(st.lists(names, min_size=1, max_size=4, unique=True))
    users = draw(st.lists(names.map(lambda n: f"u-{n}"), min_size=len(group_names), max_size=len(group_names) * 2,
                          unique=True))
    groups = [Group(name, tuple(users[i::len(group_names)]),
                    tuple(draw(st.lists(st.sampled_from(cells), max_size=len(cells), unique=True))))
              for i, name in enumerate(group_names)]
    prefix = draw(st.sampled_from(["nanodrift", "site/hall2", "femto/lab3/stages"]))
    return cells, groups, prefix


@settings(max_examples=examples(40), deadline=None)
@given(facilities())
def test_each_group_may_move_exactly_its_cells_and_every_client_may_watch_all(
        facility: tuple[list[str], list[Group], str]) -> None:
    cells, groups, prefix = facility
    block = zenoh_reads(render_block(access_control(cells, groups, prefix), "nanodrift acl ..."))
    assert block["enabled"] is True and block["default_permission"] == "deny"
    assert {r["permission"] for r in block["rules"]} == {"allow"}
    for group in groups:
        for user in group.users:
            assert allowed(block, user, "ingress", "put") == {f"{prefix}/{c}/{k}" for c in group.cells
                                                              for k in ("target", "stop")}
            assert allowed(block, user, "ingress", "query") == {f"{prefix}/*/status"} | {
                f"{prefix}/{c}/{k}" for c in group.cells for k in ("compensate", "stop")}
            assert allowed(block, user, "ingress", "declare_subscriber") == {f"{prefix}/**"}
            assert f"{prefix}/*/command" in allowed(block, user, "egress", "put")
    for cell in cells:
        daemon = f"nanodrift-{cell}"
        for message in ("put", "declare_queryable", "liveliness_token", "reply"):
            assert allowed(block, daemon, "ingress", message) == {f"{prefix}/{cell}/**"}


@settings(max_examples=examples(200), deadline=None)
@given(st.text(max_size=40))
def test_any_group_argument_is_a_group_or_a_clear_refusal(text: str) -> None:
    try:
        group = parse_group(text)
    except UserError as error:
        assert f"--group {text!r}" in str(error)
        return
    assert NAME.fullmatch(group.name) and group.users and all(USER.fullmatch(u) for u in group.users)
    assert all(NAME.fullmatch(c) for c in group.cells)
    assert parse_group(f"{group.name}={','.join(group.users)}:{','.join(group.cells)}") == group


@pytest.mark.parametrize(("cells", "groups", "prefix", "says"), [
    (["c0"], ["a=alice:c9"], "nanodrift", "--group a: cell 'c9' is not one of the --cell names"),
    (["c0"], ["a=alice:c0", "b=alice:"], "nanodrift", "user 'alice' is already in group 'a'"),
    (["c0"], ["a=nanodrift-c0:c0"], "nanodrift", "is a cell daemon's identity"),
    (["c0", "c0"], ["a=alice:c0"], "nanodrift", "--cell: c0 given twice"),
    (["c0"], ["a=alice:c0"], "site/*", "--prefix:"),
    (["c 0"], ["a=alice:"], "nanodrift", "--cell 'c 0'"),
    ([], ["a=alice:"], "nanodrift", "--cell: name at least one cell"),
    (["c0"], [], "nanodrift", "--group: name at least one"),
    (["c0"], ["a=:c0"], "nanodrift", "--group 'a=:c0': users ''"),
    (["c0"], ["a-alice-c0"], "nanodrift", "expected NAME=USER"),
])
def test_bad_arguments_are_refused_naming_what(cells: list[str], groups: list[str], prefix: str, says: str) -> None:
    with pytest.raises(UserError, match=None) as refused:
        access_control(cells, [parse_group(g) for g in groups], prefix)
    assert says in str(refused.value)


def run_acl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "nanodrift.cli", "acl", *args], capture_output=True, text=True,
                          cwd=REPO, timeout=60)


def test_into_the_shipped_secure_config_keeps_its_credentials_and_replaces_its_rules(tmp_path: Path) -> None:
    out = tmp_path / "router.json5"
    result = run_acl("--prefix", "site/hall2", "--cell", "x1", "--cell", "x2", "--group", "a=alice,bob:x1",
                     "--group", "watch=grafana:", "--into", str(SECURE), "--out", str(out))
    assert result.returncode == 0, result.stderr
    conf = zenoh.Config.from_file(str(out))
    shipped = zenoh.Config.from_file(str(SECURE))
    assert conf.get_json("transport/auth/usrpwd") == shipped.get_json("transport/auth/usrpwd")
    assert conf.get_json("scouting/multicast/enabled") == "false"
    block = json.loads(conf.get_json("access_control"))
    assert allowed(block, "bob", "ingress", "put") == {"site/hall2/x1/target", "site/hall2/x1/stop"}
    assert allowed(block, "grafana", "ingress", "put") == set()
    assert "lab-client" not in out.read_text() and "cell0-daemon" not in out.read_text()  # the old rules are gone
    assert "// written by: nanodrift acl --prefix site/hall2 --cell x1 --cell x2" in out.read_text()


def test_printed_without_into() -> None:
    result = run_acl("--cell", "c0", "--group", "a=alice:c0")
    assert result.returncode == 0, result.stderr
    block = zenoh_reads(result.stdout)
    assert allowed(block, "alice", "ingress", "put") == {"nanodrift/c0/target", "nanodrift/c0/stop"}


def test_a_refusal_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "router.json5"
    result = run_acl("--cell", "c0", "--group", "a=alice:c1", "--out", str(out))
    assert result.returncode == 2 and "cell 'c1' is not one of the --cell names" in result.stderr
    assert not out.exists()
    no_block = tmp_path / "plain.json5"
    no_block.write_text('{ mode: "router" }\n')
    result = run_acl("--cell", "c0", "--group", "a=alice:c0", "--into", str(no_block), "--out", str(out))
    assert result.returncode == 2 and f"{no_block}: no `access_control: {{` block" in result.stderr
    assert not out.exists()


def test_replace_block_skips_braces_in_strings_and_comments() -> None:
    text = ('{\n  a: "}{",\n  access_control: {\n    // a } in a comment\n    x: "{",\n    /* } */ y: {z: 1},\n  },'
            '\n  b: 2,\n}\n')
    replaced = replace_block(text, "  access_control: {},", "f.json5")
    assert replaced == '{\n  a: "}{",\n  access_control: {},\n  b: 2,\n}\n'
