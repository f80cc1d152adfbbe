"""A facility on one machine: N simulated cells behind one Zenoh router (issue 29's fleet).

The router is a zenoh session in router mode in this process, listening on 127.0.0.1; each cell is
``nanodrift run`` in its own process, a client of the router (``[zenoh] mode = "client"``), under a
two-chunk key prefix. With ``groups`` the router authenticates every session (user/password, the
credentials of ``config/zenoh-secure.json5``) and enforces the access control that ``nanodrift acl``
writes into a copy of that file; each daemon logs in as ``nanodrift-<cell>``, each group's users get a
client config of their own (``config/zenoh-client.example.json5`` with their credentials).

The cells are the simulated cell run light: three temperature channels polled once a second, no
interferometer (so no health loop), the shipped model. Measured on this 2-core machine (idle, 20 s
of /proc/<pid>/stat): the shipped ``config/sim.toml`` daemon uses 0.6 % of a core and this one
0.15 %; both take about 0.55 s of CPU to start (mostly imports) and 77 MB resident. The 20-cell
fleet test uses about 15 s of CPU in all (its daemons, the router, pytest): at best ~8 s of wall on two
idle cores (CPU / 2, not measured: the machine was never idle), 35-45 s measured with the load
average at 10-15 from other jobs.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from helpers.daemon_harness import REPO, Daemon, free_port, run_cli, wait_until

CONFIG = REPO / "config"
PREFIX = "site/hall2"
SHIPPED_DICTIONARY = "/etc/nanodrift/zenoh-credentials.txt"


def cell_name(index: int) -> str:
    return f"cell{index:02d}"


def light_cell_config(cell: str, router_port: int, prefix: str, zenoh_file: Path | None) -> str:
    """A simulated cell, client of the router, with three temperature channels polled once a second."""
    sensors = "".join(f'\n[[sensors]]\nname = "{channel}"\nkind = "simulated"\ninterval_s = 1.0\nmax_age_s = 5.0\n'
                      for channel in ("T1", "T2", "T3", "T4"))  # all four: whichever the shipped model uses
    zenoh_lines = f'config_file = "{zenoh_file}"\n' if zenoh_file is not None else ""
    return (f'cell = "{cell}"\n[zenoh]\nmode = "client"\nconnect = ["tcp/127.0.0.1:{router_port}"]\n'
            f'multicast_scouting = false\nprefix = "{prefix}"\n{zenoh_lines}'
            f'[simulation]\nscenario = "room"\nspeed = 1.0\n{sensors}')


def credentials_config(path: Path, user: str, password: str, template: Path = CONFIG / "zenoh-client.example.json5"
                       ) -> Path:
    """The shipped client config with this user's credentials (its endpoint is replaced by ``-e``)."""
    text = template.read_text()
    for old, new in (('user: "lab-client"', f'user: "{user}"'),
                     ('password: "CHANGE-ME-client-password"', f'password: "{password}"')):
        assert old in text, f"{template.name} changed: {old!r}"
        text = text.replace(old, new)
    path.write_text(text)
    return path


def password_of(user: str) -> str:
    return f"pw-{user}"


@dataclass
class Fleet:
    """Start with :meth:`start`; ``groups`` (name -> (users, cells)) turns authentication and the ACL on."""

    root: Path
    cells: int
    prefix: str = PREFIX
    groups: dict[str, tuple[list[str], list[str]]] | None = None
    router_port: int = field(default_factory=free_port)
    names: list[str] = field(default_factory=list)
    daemons: dict[str, Daemon] = field(default_factory=dict)
    user_configs: dict[str, Path] = field(default_factory=dict)
    router: zenoh.Session | None = None

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.router_port}"

    def start(self, timeout_s: float = 90.0) -> Fleet:
        self.root.mkdir(parents=True, exist_ok=True)
        self.names = [cell_name(i) for i in range(self.cells)]
        try:
            self.router = zenoh.open(self._router_config())
            for cell in self.names:
                self.daemons[cell] = self._start_daemon(cell)
            for daemon in self.daemons.values():
                daemon.wait_log("serving", timeout=timeout_s)
            wait_until(lambda: self.alive_cells() == set(self.names), timeout_s, f"{self.cells} alive tokens",
                       interval=0.1)
        except BaseException:
            self.close()
            raise
        return self

    def _router_config(self) -> zenoh.Config:
        if self.groups is None:
            conf = zenoh.Config()
        else:
            conf = zenoh.Config.from_file(str(self._write_acl_router_config()))
        conf.insert_json5("mode", json.dumps("router"))
        conf.insert_json5("listen/endpoints", json.dumps([self.endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        return conf

    def _write_acl_router_config(self) -> Path:
        """``nanodrift acl`` into a copy of the shipped secure config, and the credentials of every user."""
        assert self.groups is not None
        users = [f"nanodrift-{c}" for c in self.names] + [u for users, _ in self.groups.values() for u in users]
        dictionary = self.root / "credentials.txt"
        dictionary.write_text("".join(f"{u}:{password_of(u)}\n" for u in users))
        base = self.root / "zenoh-secure.json5"
        text = (CONFIG / "zenoh-secure.json5").read_text()
        assert text.count(SHIPPED_DICTIONARY) == 1
        base.write_text(text.replace(SHIPPED_DICTIONARY, str(dictionary)))
        router_file = self.root / "router.json5"
        args = ["acl", "--prefix", self.prefix, "--into", str(base), "--out", str(router_file),
                *(a for c in self.names for a in ("--cell", c))]
        for name, (members, cells) in self.groups.items():
            args += ["--group", f"{name}={','.join(members)}:{','.join(cells)}"]
            for user in members:
                self.user_configs[user] = credentials_config(self.root / f"{user}.json5", user, password_of(user))
        result = run_cli(*args, cwd=REPO)  # it writes a file: no process of its own needed
        assert result.returncode == 0, result.stderr
        return router_file

    def _start_daemon(self, cell: str) -> Daemon:
        zenoh_file = None
        if self.groups is not None:
            user = f"nanodrift-{cell}"
            zenoh_file = credentials_config(self.root / f"{cell}-zenoh.json5", user, password_of(user))
        config = self.root / f"{cell}.toml"
        config.write_text(light_cell_config(cell, self.router_port, self.prefix, zenoh_file))
        return Daemon(["--config", str(config)], self.root / f"{cell}.log")

    def alive_cells(self) -> set[str]:
        assert self.router is not None
        replies = self.router.liveliness().get(f"{self.prefix}/*/alive", timeout=1.0)
        return {str(r.ok.key_expr).split("/")[-2] for r in replies if r.ok is not None}

    def status_of(self, cell: str) -> dict[str, object]:
        """A cell's status asked by the router's own session (local to it: no access control applies)."""
        assert self.router is not None
        replies = [r for r in self.router.get(f"{self.prefix}/{cell}/status", timeout=5.0) if r.ok is not None]
        assert len(replies) == 1, f"{cell}: {len(replies)} status replies"
        doc = json.loads(replies[0].ok.payload.to_bytes())
        assert isinstance(doc, dict)
        return doc

    def close(self) -> dict[str, int]:
        """Stop every daemon (their exit codes by cell), then the router."""
        codes = {}
        for daemon in self.daemons.values():  # all at once: they shut down in parallel
            if daemon.proc.poll() is None:
                daemon.proc.terminate()
        for cell, daemon in self.daemons.items():
            try:
                daemon.proc.wait(30)  # a second SIGTERM (Daemon.stop's) would kill one still shutting down
            except subprocess.TimeoutExpired:
                pass  # Daemon.stop kills it
            codes[cell] = daemon.stop()
        if self.router is not None:
            self.router.close()
            self.router = None
        return codes
