"""A Zenoh subscriber in its own process that a test can freeze (SIGSTOP) while it is subscribed.

``python -m helpers.stalled_client PORT CELL``: a client-mode session on ``tcp/127.0.0.1:PORT``
subscribed to the cell's ``command`` key, with a tiny TCP receive buffer (so a frozen process fills
its pipe after a few hundred kB) and a long lease (so the daemon keeps it connected while frozen,
and a stall cannot end because the link was dropped). It answers one line per request on stdin:
``count`` -> the number of commands received; ``seen ID`` -> ``yes``/``no`` for a command id.

:class:`StalledClient` runs it and asks it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import zenoh

TESTS = Path(__file__).resolve().parents[1]
REPO = TESTS.parent
LEASE_MS = 120_000


def session_config(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/tcp/so_rcvbuf", "4096")
    conf.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    return conf


def main(port: int, cell: str) -> None:
    lock = threading.Lock()
    ids: set[object] = set()

    def on_command(sample: zenoh.Sample) -> None:
        command_id = json.loads(sample.payload.to_bytes()).get("id")
        with lock:
            ids.add(command_id)

    session = zenoh.open(session_config(port))
    session.declare_subscriber(f"nanodrift/{cell}/command", on_command)
    print("ready", flush=True)
    for line in sys.stdin:
        request, _, arg = line.strip().partition(" ")
        with lock:
            if request == "count":
                print(len(ids), flush=True)
            elif request == "seen":
                print("yes" if arg in ids else "no", flush=True)
    session.close()


class StalledClient:
    """The subscriber process; ``stop()``/``cont()`` freeze and thaw it."""

    def __init__(self, port: int, cell: str) -> None:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(REPO)])}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "helpers.stalled_client", str(port), cell],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=str(REPO),
        )
        if self._readline() != "ready":
            raise AssertionError("the stalled client did not start")

    def _readline(self) -> str:
        assert self.proc.stdout is not None
        return self.proc.stdout.readline().strip()

    def ask(self, request: str) -> str:
        assert self.proc.stdin is not None
        self.proc.stdin.write(request + "\n")
        self.proc.stdin.flush()
        return self._readline()

    def count(self) -> int:
        return int(self.ask("count"))

    def seen(self, command_id: str) -> bool:
        return self.ask(f"seen {command_id}") == "yes"

    def stop(self) -> None:
        os.kill(self.proc.pid, signal.SIGSTOP)

    def cont(self) -> None:
        os.kill(self.proc.pid, signal.SIGCONT)

    def close(self) -> None:
        self.cont()
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2])
