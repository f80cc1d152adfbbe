"""A TCP port on 127.0.0.1 for a listener that another process binds a moment later (the demo's daemon, a
test's daemon or device emulator, a benchmark's peer).

The port the kernel hands out for ``bind(("127.0.0.1", 0))`` comes from its ephemeral range, the same range
it draws the source port of every outgoing connection from. Between that pick and the listener's own bind,
any ``connect()`` on the machine can take the port (a CI run with four test workers saw a daemon fail with
"already in use" this way). The ports here come from below that range, where only an explicit bind can land.
Each process walks its own stretch (its pid spreads processes apart) and skips ports bound right now,
including ones a listener closed a moment ago.
"""

from __future__ import annotations

import os
import socket
import threading
from pathlib import Path

EPHEMERAL_RANGE_PATH = Path("/proc/sys/net/ipv4/ip_local_port_range")
#: Linux's default ephemeral floor; macOS and Windows start theirs higher still (49152)
DEFAULT_EPHEMERAL_FLOOR = 32768
#: the lowest port handed out: above the registered services most labs run (databases, web, EPICS 5064/5065)
LOWEST_PORT = 15000
#: a process's walk starts this many ports from the last process's start (pids are often consecutive)
PROCESS_STRIDE = 997

_lock = threading.Lock()
_walk = {"pid": 0, "next": 0}  # a forked child starts its own walk (its pid differs)


def ephemeral_floor() -> int:
    """The lowest port the kernel picks for outgoing connections and ``bind(0)``."""
    try:
        return int(EPHEMERAL_RANGE_PATH.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return DEFAULT_EPHEMERAL_FLOOR


def _bindable(port: int) -> bool:
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _kernel_pick() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody has bound right now, outside the ephemeral range when the machine
    leaves room below it (else the kernel's own pick)."""
    span = ephemeral_floor() - LOWEST_PORT
    if span < 2 * PROCESS_STRIDE:
        return _kernel_pick()
    with _lock:
        if _walk["pid"] != os.getpid():
            _walk.update(pid=os.getpid(), next=(os.getpid() * PROCESS_STRIDE) % span)
        for _ in range(span):
            port = LOWEST_PORT + _walk["next"] % span
            _walk["next"] = (_walk["next"] + 1) % span
            if _bindable(port):
                return port
    return _kernel_pick()
