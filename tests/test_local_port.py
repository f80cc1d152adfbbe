"""The ports handed to listeners started by another process: never where an outgoing connection can land."""

from __future__ import annotations

import socket

import pytest

from nanodrift.drivers import local_port
from nanodrift.drivers.local_port import LOWEST_PORT, ephemeral_floor, free_port


def test_ports_come_from_below_the_ephemeral_range_and_are_bindable() -> None:
    ports = [free_port() for _ in range(50)]
    assert len(set(ports)) == 50, "a port handed out twice in one process"
    assert all(LOWEST_PORT <= port < ephemeral_floor() for port in ports), ports
    for port in ports:
        with socket.socket() as listener:
            listener.bind(("127.0.0.1", port))


def test_a_port_someone_has_bound_is_skipped() -> None:
    first = free_port()
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", first + 1))  # the next one on this process's walk (a listener of another)
        holder.listen()
        assert free_port() == first + 2


def test_processes_with_neighbouring_pids_walk_apart(monkeypatch: pytest.MonkeyPatch) -> None:
    """xdist workers (pids often consecutive) each pick ports: their walks start a stride apart."""
    walks = []
    for pid in (4000, 4001):
        monkeypatch.setattr(local_port.os, "getpid", lambda pid=pid: pid)
        walks.append({free_port() for _ in range(200)})
    assert not walks[0] & walks[1]


def test_without_room_below_the_ephemeral_range_the_kernel_picks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(local_port, "ephemeral_floor", lambda: LOWEST_PORT + 10)
    port = free_port()
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", port))
