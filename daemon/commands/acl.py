"""``nanodrift acl``: the Zenoh access control for a facility of cells and client groups.

Writing an ACL by hand for tens of cells is how a group ends up able to move another group's stage.
This command writes Zenoh 1.x's ``access_control`` block (the format of ``config/zenoh-secure.json5``)
from two lists: the cells (each cell's daemon authenticates as ``nanodrift-<cell>``) and the client
groups (``NAME=USER,USER:CELL,CELL``: those users may put ``target``/``stop`` and query
``compensate``/``stop`` on those cells only; a group with no cells only watches). Every client may
read every cell: ``status``, ``command``, ``error``, ``done``, ``health``, ``sensors/**``, ``alive``.

It is an allow list with ``default_permission: "deny"`` (a deny rule matches only messages whose
key it includes, so a put on ``<prefix>/**`` would pass a deny list: see the shipped file). A cell's
daemon may send only under its own ``<prefix>/<cell>/**``, so a leaked daemon password cannot speak
for another cell; what the router forwards *to* daemons is any key under the prefix (their
subscriptions and queryables select what they receive; other cells' ``status`` queries use a
wildcard that no single cell's keys include).

``--into F`` puts the block into a copy of a Zenoh config (``config/zenoh-secure.json5``: its
credentials, TLS and scouting stay), replacing the ``access_control`` block it has; without it the
block alone is printed, to paste. The router (or the one daemon every client connects to) is where
Zenoh applies it: put it in that process' config.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nanodrift.atomic import atomic_write_text
from nanodrift.errors import UserError
from nanodrift.settings import DEFAULT_PREFIX, checked_prefix

#: a cell or group name (the config's ``cell`` pattern) and a Zenoh user name (no separators of this syntax)
NAME = re.compile(r"[A-Za-z0-9_\-]+")
USER = re.compile(r"[A-Za-z0-9_.@\-]+")
#: every message kind Zenoh's access control knows (1.x)
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]
#: what a daemon publishes to every client; a key added to the contract must be added here
TELEMETRY = ["command", "error", "done", "health", "sensors/**"]


@dataclass(frozen=True)
class Group:
    """Client users who may move ``cells`` (and, like every client, watch all of them)."""

    name: str
    users: tuple[str, ...]
    cells: tuple[str, ...]


def daemon_user(cell: str) -> str:
    """The user a cell's daemon authenticates as (``[zenoh] config_file``'s ``usrpwd.user``)."""
    return f"nanodrift-{cell}"


def parse_group(text: str) -> Group:
    """``NAME=USER[,USER...]:CELL[,CELL...]`` (the cells may be empty: a group that only watches)."""
    expected = "expected NAME=USER[,USER...]:CELL[,CELL...], e.g. beamline-a=alice,bob:cell0,cell1"
    name, equals, rest = text.partition("=")
    users, colon, cells = rest.partition(":")
    if not equals or not colon:
        raise UserError(f"--group {text!r}: {expected}")
    if not NAME.fullmatch(name):
        raise UserError(f"--group {text!r}: group name {name!r} is not letters, digits, '_' or '-'; {expected}")
    user_list = tuple(u for u in users.split(",") if u)
    if not user_list or any(not USER.fullmatch(u) for u in user_list):
        raise UserError(f"--group {text!r}: users {users!r}: one or more user names separated by ','; {expected}")
    cell_list = tuple(c for c in cells.split(",") if c)
    for cell in cell_list:
        if not NAME.fullmatch(cell):
            raise UserError(f"--group {text!r}: cell {cell!r} is not letters, digits, '_' or '-'")
    return Group(name, user_list, cell_list)


def check(cells: list[str], groups: list[Group], prefix: str) -> None:
    """Every name once, every group's cell a listed cell, no user in two groups: else a UserError naming it."""
    checked_prefix(prefix, label="--prefix: ", error=UserError)
    if not cells:
        raise UserError("--cell: name at least one cell (--cell cell0 --cell cell1 ...)")
    for cell in cells:
        if not NAME.fullmatch(cell):
            raise UserError(f"--cell {cell!r}: a cell name is letters, digits, '_' or '-' (the config's `cell`)")
    for what, names in (("--cell", cells), ("--group", [g.name for g in groups])):
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise UserError(f"{what}: {', '.join(repeated)} given twice")
    if not groups:
        raise UserError("--group: name at least one client group (NAME=USER,...:CELL,...)")
    owner: dict[str, str] = {}
    for group in groups:
        unknown = [c for c in group.cells if c not in cells]
        if unknown:
            raise UserError(f"--group {group.name}: cell {unknown[0]!r} is not one of the --cell names {cells}")
        for user in group.users:
            if user in owner:
                raise UserError(f"--group {group.name}: user {user!r} is already in group {owner[user]!r}: "
                                "a user's rights would be the union of both; give it one group")
            if user in {daemon_user(c) for c in cells}:
                raise UserError(f"--group {group.name}: user {user!r} is a cell daemon's identity")
            owner[user] = group.name


def access_control(cells: list[str], groups: list[Group], prefix: str = DEFAULT_PREFIX) -> dict[str, Any]:
    """Zenoh 1.x's ``access_control`` block (a dict to render as JSON5) for these cells and groups."""
    check(cells, groups, prefix)
    every = f"{prefix}/*"
    rules: list[dict[str, Any]] = [
        _rule("client-watches", "ingress",
              ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"], [f"{prefix}/**"]),
        _rule("client-queries-status", "ingress", ["query"], [f"{every}/status"]),
        _rule("client-receives-samples", "egress", ["put"], [f"{every}/{key}" for key in TELEMETRY]),
        _rule("client-receives-replies", "egress", ["reply", "declare_queryable"],
              [f"{every}/compensate", f"{every}/status", f"{every}/stop"]),
        _rule("client-sees-alive", "egress", ["liveliness_token"], [f"{every}/alive"]),
        _rule("client-finds-target-subscriber", "egress", ["declare_subscriber"], [f"{every}/target", f"{every}/stop"]),
        _rule("daemons-receive", "egress", ALL_MESSAGES, [f"{prefix}/**"]),
    ]
    client_rules = [r["id"] for r in rules if r["id"].startswith("client-")]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for group in groups:
        subjects.append({"id": f"group-{group.name}", "usernames": list(group.users)})
        own = []
        if group.cells:
            own = [f"group-{group.name}-moves", f"group-{group.name}-queries"]
            rules.append(_rule(own[0], "ingress", ["put"],
                               [f"{prefix}/{c}/{key}" for c in group.cells for key in ("target", "stop")]))
            rules.append(_rule(own[1], "ingress", ["query"],
                               [f"{prefix}/{c}/{key}" for c in group.cells for key in ("compensate", "stop")]))
        policies.append({"id": f"group-{group.name}", "rules": [*client_rules, *own],
                         "subjects": [f"group-{group.name}"]})
    for cell in cells:
        rules.append(_rule(f"{cell}-daemon-sends", "ingress", ALL_MESSAGES, [f"{prefix}/{cell}/**"]))
        subjects.append({"id": f"{cell}-daemon", "usernames": [daemon_user(cell)]})
        policies.append({"id": f"{cell}-daemon", "rules": [f"{cell}-daemon-sends", "daemons-receive"],
                         "subjects": [f"{cell}-daemon"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}


def render_block(block: dict[str, Any], command: str, indent: str = "  ") -> str:
    """``access_control: {...},`` as JSON5 text (JSON is JSON5; a list of names on one line), indented to sit
    in a config's top level, after a comment saying which command wrote it."""
    body = json.dumps(block, indent=2)
    body = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]", lambda m: "[" + ", ".join(s.strip() for s in m[1].split(",\n")) + "]",
                  body)
    return f"{indent}// written by: {command}\n{indent}access_control: " + body.replace("\n", "\n" + indent) + ","


def replace_block(config_text: str, block_text: str, source: str) -> str:
    """``config_text`` with its top-level ``access_control: {...},`` replaced by ``block_text``."""
    found = re.search(r"^[ \t]*access_control\s*:\s*\{", config_text, re.MULTILINE)
    if found is None:
        raise UserError(f"{source}: no `access_control: {{` block to replace (expected a Zenoh config like "
                        "config/zenoh-secure.json5)")
    end = _closing_brace(config_text, found.end() - 1, source)
    tail = re.match(r"\s*,?", config_text[end + 1:])
    assert tail is not None
    return config_text[:found.start()] + block_text + config_text[end + 1 + tail.end():]


def _closing_brace(text: str, start: int, source: str) -> int:
    """The index of the ``}`` closing the ``{`` at ``start``, skipping strings and ``//`` / ``/* */`` comments."""
    depth, index = 0, start
    while index < len(text):
        char = text[index]
        if char in "\"'":  # to the closing quote, over escaped characters
            index += 1
            while index < len(text) and text[index] != char:
                index += 2 if text[index] == "\\" else 1
        elif text.startswith("//", index):
            index = text.find("\n", index)
            index = len(text) if index < 0 else index
        elif text.startswith("/*", index):
            index = text.find("*/", index)
            index = len(text) if index < 0 else index + 1
        elif char == "{":
            depth += 1
        elif char == "}":
            depth -= 1
            if depth == 0:
                return index
        index += 1
    raise UserError(f"{source}: the access_control block's braces do not close")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = ("Example: nanodrift acl --prefix site/hall2 --cell cell0 --cell cell1 --cell cell2 "
                     "--group beamline-a=alice,bob:cell0,cell1 --group beamline-b=carol:cell2 "
                     "--group monitoring=grafana: --into config/zenoh-secure.json5 --out router.json5")
    parser.add_argument("--cell", action="append", default=[], metavar="C",
                        help="a cell (repeat); its daemon authenticates as nanodrift-<C>")
    parser.add_argument("--group", action="append", default=[], metavar="NAME=USERS:CELLS",
                        help="a client group (repeat): its users (comma-separated) may move these cells "
                             "(comma-separated; none: watch only). Every client may read every cell")
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, metavar="P", help="the cells' [zenoh] prefix")
    parser.add_argument("--into", metavar="F", help="a Zenoh json5 config whose access_control block is replaced "
                                                    "(e.g. config/zenoh-secure.json5)")
    parser.add_argument("--out", metavar="F", help="write here (atomically) instead of printing")


def main(args: argparse.Namespace) -> int:
    groups = [parse_group(text) for text in args.group]
    command = " ".join(["nanodrift acl", f"--prefix {args.prefix}", *(f"--cell {c}" for c in args.cell),
                        *(f"--group {g}" for g in args.group)])
    block = render_block(access_control(list(args.cell), groups, args.prefix), command)
    if args.into:
        try:
            text = Path(args.into).read_text(encoding="utf-8")
        except OSError as err:
            raise UserError(f"--into {args.into}: cannot read it ({err.strerror or err})") from None
        block = replace_block(text, block, args.into)
    elif not block.endswith("\n"):
        block += "\n"
    if args.out:
        try:
            atomic_write_text(args.out, block)
        except OSError as err:
            raise UserError(f"--out {args.out}: cannot write it ({err.strerror or err})") from None
        print(f"{args.out}: access control for {len(args.cell)} cells and {len(groups)} groups", file=sys.stderr)
    else:
        sys.stdout.write(block)
    return 0
