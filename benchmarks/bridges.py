"""What the bridges add to a move: ``nanodrift.Client.move`` (the baseline), a Bluesky ``bps.mv`` of
``nanodrift.bluesky.Stage``, and a Channel Access put to ``SP`` until ``DMOV`` returns to 1 (``nanodrift ioc``).

One simulated one-axis cell (``nanodrift run``, no slew: a move is done once its command is published and
applied), each path timed over the same alternating targets in the same run, p50 and p99 of the wall time
from the request to the move's end, and each path's ratio to the client's. The Stage's ``set`` also waits
for the first position sample after the ``done`` (the simulated interferometer reads every 0.1 s), so its
figure includes that wait; the CA path includes the bridge's worker-thread hop and two CA messages.

    python benchmarks/bridges.py [--moves 40]
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from nanodrift.drivers.local_port import free_port

REPO = Path(__file__).resolve().parent.parent


def start(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "nanodrift.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=open(log, "wb"), env=env, cwd=REPO)


def wait_for(predicate: Callable[[], Any], timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise SystemExit(f"timed out waiting for {what}")


def figures(name: str, times_s: list[float], baseline_p50_s: float | None) -> float:
    p50 = statistics.median(times_s)
    p99 = sorted(times_s)[max(0, round(0.99 * len(times_s)) - 1)]
    ratio = f", {p50 / baseline_p50_s:.1f}x the client" if baseline_p50_s else ""
    print(f"{name:<36} p50 {p50 * 1000:7.1f} ms   p99 {p99 * 1000:7.1f} ms   ({len(times_s)} moves{ratio})")
    return p50


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--moves", type=int, default=40)
    options = parser.parse_args()
    from nanodrift import Client

    root = Path(tempfile.mkdtemp(prefix="nanodrift-bridges-"))
    port, ca_port = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    (root / "cell.toml").write_text(f'cell = "bench"\n[zenoh]\nmode = "peer"\nlisten = ["{endpoint}"]\n'
                                    'multicast_scouting = false\n[simulation]\nscenario = "room"\nspeed = 1.0\n')
    ca_env = {"EPICS_CA_ADDR_LIST": f"127.0.0.1:{ca_port}", "EPICS_CA_AUTO_ADDR_LIST": "NO",
              "EPICS_CAS_INTF_ADDR_LIST": "127.0.0.1", "EPICS_CA_SERVER_PORT": str(ca_port),
              "EPICS_CAS_AUTO_BEACON_ADDR_LIST": "NO", "EPICS_CAS_BEACON_ADDR_LIST": "127.0.0.1",
              "EPICS_CAS_BEACON_PORT": str(free_port())}
    env = {**os.environ, **ca_env}
    daemon = start(["run", "--config", str(root / "cell.toml")], env, root / "daemon.log")
    ioc: subprocess.Popen[bytes] | None = None
    targets = [100.0 + 100.0 * (i % 2) for i in range(options.moves)]
    try:
        client = wait_for(lambda: _client(Client, endpoint), 30, "the daemon")
        wait_for(lambda: _ready(client), 30, "the cell's sensors")
        baseline = []
        for x in targets:
            t0 = time.perf_counter()
            client.move(x)
            baseline.append(time.perf_counter() - t0)
        base_p50 = figures("nanodrift.Client.move", baseline, None)

        from bluesky import RunEngine
        from bluesky import plan_stubs as bps
        from ophyd_async.core import init_devices

        from nanodrift.bluesky import Stage

        engine = RunEngine({})
        with init_devices():
            stage = Stage(endpoint, "bench", name="stage")
        moved = []
        for x in targets:
            t0 = time.perf_counter()
            engine(bps.mv(stage, x))
            moved.append(time.perf_counter() - t0)
        stage.close()
        figures("Bluesky RE(bps.mv(Stage))", moved, base_p50)

        ioc = start(["ioc", "-e", endpoint, "--cell", "bench", "--pv-prefix", "bench:"], env, root / "ioc.log")
        wait_for(lambda: "serving cell" in (root / "ioc.log").read_text(), 30, "nanodrift ioc")
        os.environ.update(ca_env)
        from caproto.threading.client import Context

        context = Context()
        sp, dmov = context.get_pvs("bench:bench:SP", "bench:bench:DMOV", timeout=10)
        for pv in (sp, dmov):
            pv.wait_for_connection(timeout=10)
        values: list[int] = []
        changed = threading.Condition()
        subscription = dmov.subscribe(data_type="native")

        def on_dmov(sub: Any, response: Any) -> None:
            with changed:
                values.append(int(response.data[0]))
                changed.notify_all()

        subscription.add_callback(on_dmov)
        put = []
        for x in targets:
            with changed:
                before = len(values)
            t0 = time.perf_counter()
            sp.write([x], wait=True, timeout=10)
            with changed:  # this move's 0, then a 1 after it
                if not changed.wait_for(lambda start=before: 0 in values[start:] and values[-1] == 1, 10):
                    raise SystemExit(f"DMOV did not go 0 then 1 after the put of {x}")
            put.append(time.perf_counter() - t0)
        subscription.clear()
        context.disconnect()
        figures("CA put SP -> DMOV 1 (nanodrift ioc)", put, base_p50)
        client.close()
    finally:
        for process in (ioc, daemon):
            if process is not None and process.poll() is None:
                process.send_signal(signal.SIGTERM)
                process.wait(10)
    return 0


def _client(client_class: Any, endpoint: str) -> Any:
    try:
        return client_class(endpoint, cell="bench")
    except ConnectionError:
        return None


def _ready(client: Any) -> bool:
    try:
        sensors = client.status(timeout_s=1.0)["sensors"]
    except TimeoutError:
        return False
    return all(s["state"] == "ok" for s in sensors.values())


if __name__ == "__main__":
    sys.exit(main())
