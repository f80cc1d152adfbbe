"""Round trip target -> command through the daemon, against a bare Zenoh echo node (the floor).

One run, side by side, on this machine:
- the daemon (``python -m nanodrift.cli run``, simulated cell, shipped model) and a bare echo node
  (a subscriber that republishes each payload from Zenoh's callback thread), each in its own process,
  each reached by a client-mode session over tcp/127.0.0.1;
- p50/p99 of the round trip at 1 kHz (targets paced at 1 ms by sleeping: a client spinning between sends held
  the GIL while its own answer callback waited, and stamped every answer later than ~0.7 ms at the next send,
  ~1 ms, so the p99 measured the client), a burst of targets sent as fast as
  possible (answers lost are counted), and the daemon's idle CPU (% of one core over 10 s) and RSS.

The daemon encodes and puts a ``done`` for every served command (on the target's thread, after its answer, for
the one it replaced); nobody receives them unless ``--done-subscriber`` (then the daemons' probers subscribe,
as ``nanodrift.Client`` does).

Budget: p50 within 1.3x of the echo, p99 within 1.5x, nothing lost in the burst.

``--axes N`` (2 or 3) adds a multi-axis cell (``[[axes]]`` x, y[, z], ``kind = "zenoh"`` outputs, a
hand-made cell model with cross terms) and a one-axis cell on the same sensors (two temperatures in a
Modbus module emulated in a process of its own), each its own daemon, measured in the same alternating rounds:
the multi-axis cell's p50 must be within 1.2x of the one-axis cell's.

    .venv/bin/python benchmarks/daemon_latency.py [--paced 3000] [--burst 5000] [--idle-s 10] [--axes 3]
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import json
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from nanodrift.assembly import build_drivers
from nanodrift.config import load_config
from nanodrift.drivers.local_port import free_port
from nanodrift.logs import configure_logging
from nanodrift.service import Service
from nanodrift.service.status import StatusHandler
from nanodrift.service.targets import TargetHandler

REPO = Path(__file__).resolve().parent.parent
ECHO_IN, ECHO_OUT = "bench/echo/target", "bench/echo/command"
ROUND = 100  # paced targets per alternating round


def zconf(mode: str, *, listen: str | None = None, connect: str | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps([listen]))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps([connect]))
    return conf


def echo_node(port: int) -> None:
    """The floor: receive a target, publish it back, from Zenoh's own thread; nothing else."""
    session = zenoh.open(zconf("peer", listen=f"tcp/127.0.0.1:{port}"))
    publisher = session.declare_publisher(ECHO_OUT, congestion_control=zenoh.CongestionControl.BLOCK, express=True)
    session.declare_subscriber(ECHO_IN, lambda sample: publisher.put(sample.payload.to_bytes()))
    print("ready", flush=True)
    sys.stdin.read()  # until the parent closes our stdin
    session.close()


class TargetsOnLoop(Service):
    """The daemon with each target handed to its asyncio loop before it is answered (one more thread
    hop): the variant ``--targets-on-loop`` measures, to show why targets are answered on Zenoh's thread."""

    def serve(self, loop: asyncio.AbstractEventLoop, targets: TargetHandler, status: StatusHandler) -> None:
        assert self.bus is not None
        self.bus.serve(loop, functools.partial(loop.call_soon_threadsafe, targets.on_target),  # type: ignore[arg-type]
                       status.on_status)


def daemon_on_loop(config_path: str) -> int:
    configure_logging("info")

    async def main() -> int:
        return await TargetsOnLoop(load_config(config_path), config_path=config_path, build_drivers=build_drivers).run()

    return asyncio.run(main())


class Prober:
    """Sends targets on ``key_in`` and timestamps each answer on ``key_out`` (and ``key_err``) by id."""

    def __init__(self, port: int, key_in: str, key_out: str, key_err: str | None = None,
                 key_done: str | None = None) -> None:
        self.session = zenoh.open(zconf("client", connect=f"tcp/127.0.0.1:{port}"))
        self.received: dict[int, float] = {}
        self.errors = 0
        self._cond = threading.Condition()
        self.publisher = self.session.declare_publisher(
            key_in, congestion_control=zenoh.CongestionControl.BLOCK, express=True
        )
        self.subs = [self.session.declare_subscriber(key_out, self._answer)]
        if key_err:
            self.subs.append(self.session.declare_subscriber(key_err, self._error))
        self.dones = 0  # ``done`` messages received (``--done-subscriber``)
        if key_done:
            self.subs.append(self.session.declare_subscriber(key_done, self._done))

    def _answer(self, sample: zenoh.Sample) -> None:
        now = time.perf_counter()
        target_id = json.loads(sample.payload.to_bytes())["id"]
        with self._cond:
            self.received[target_id] = now
            self._cond.notify_all()

    def _done(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.dones += 1

    def _error(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.errors += 1
            self._cond.notify_all()

    def wait_count(self, count: int, timeout: float) -> int:
        deadline = time.monotonic() + timeout
        with self._cond:
            while len(self.received) + self.errors < count and time.monotonic() < deadline:
                self._cond.wait(max(0.0, deadline - time.monotonic()))
            return len(self.received)

    #: the target's payload: position(s) then id (a multi-axis cell's names every axis)
    template = b'{"x_um": %.3f, "id": %d}'

    def run(self, n: int, period_s: float, first_id: int) -> list[float]:
        """Send ``n`` targets every ``period_s`` (0: as fast as possible); round trips in seconds."""
        self.received.clear()
        self.errors = 0
        sent: dict[int, float] = {}
        start = time.perf_counter()
        for i in range(n):
            # paced by sleeping, never spinning: a spin holds the GIL, and an answer arriving meanwhile waits
            # for it in Zenoh's callback thread, stamped at the next send (~1 ms): the p99 measured this client
            delay_s = start + i * period_s - time.perf_counter()
            if delay_s > 0:
                time.sleep(delay_s)
            target_id = first_id + i
            x = 40.0 + (i % 400)
            payload = (self.template % (x, target_id) if self.template.count(b"%") == 2
                       else self.template % ((x,) * (self.template.count(b"%") - 1) + (target_id,)))
            sent[target_id] = time.perf_counter()
            self.publisher.put(payload)
        self.wait_count(n, timeout=10.0 + n * 0.002)
        with self._cond:
            return [self.received[k] - sent[k] for k in sent if k in self.received]

    def close(self) -> None:
        self.session.close()


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    index = min(len(ordered) - 1, max(0, round(q / 100.0 * (len(ordered) - 1))))
    return ordered[index]


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks  # utime + stime


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def wait_line(proc: subprocess.Popen[Any], stream_path: Path | None, needle: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"process exited early ({proc.returncode})")
        if stream_path is not None and needle in stream_path.read_text(errors="replace"):
            return
        time.sleep(0.05)
    raise SystemExit(f"timed out waiting for {needle!r}")


# --- --axes N: a multi-axis cell beside a one-axis cell on the same sensors --------------------------


def write_models(tmp: Path, axes: tuple[str, ...]) -> tuple[Path, Path]:
    """A one-axis model and an N-axis cell model (every axis: its position, the next axis', their product,
    T1, T2), both in the range the benchmark's targets and temperatures stay in."""
    from nanodrift.model.cell_model import CellModel, save_cell_model
    from nanodrift.model.model import FittedTerm, Model, Training, save_model
    from nanodrift.model.terms import parse_term

    ranges = {"T1": (20.0, 25.0), "T2": (20.0, 25.0)}

    def model(terms: dict[str, float], cell_axes: tuple[str, ...]) -> Model:
        training = Training(x_range=(0.0, 480.0), channel_ranges=dict(ranges), rows=100, t_span_s=3600.0,
                            position_ranges={a: (0.0, 480.0) for a in cell_axes if a != "x"})
        return Model(terms=[FittedTerm(parse_term(n, cell_axes), c) for n, c in terms.items()], training=training)

    one = tmp / "one_axis.json"
    save_model(model({"x": 1.002, "x^2": -1e-5, "T1": -0.6, "T2": -0.5, "1": 0.5}, ("x",)), one)
    models = {}
    for i, axis in enumerate(axes):
        other = axes[(i + 1) % len(axes)]
        models[axis] = model({axis: 1.002, f"{axis}^2": -1e-5, other: 0.0025, "*".join(sorted((axis, other))): 2e-6,
                              "T1": -0.6, "T2": -0.5, "1": 0.5}, axes)
    cell = tmp / "cell.json"
    save_cell_model(CellModel(axes, models), cell)
    return one, cell


def modbus_temperatures() -> tuple[int, Any]:
    """T1 and T2 (int16, 0.01 degC) in input registers 0 and 1 of an emulated module in a process of its own: in
    this one its server thread took the GIL from the probers' answer callbacks, which stamped answers late."""
    node = subprocess.Popen([sys.executable, __file__, "--modbus-node"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert node.stdout is not None and node.stdin is not None
    line = node.stdout.readline().strip()
    if not line.isdigit():
        raise SystemExit("the emulated Modbus module did not start")

    def stop() -> None:
        assert node.stdin is not None
        node.stdin.close()
        node.wait(10)

    return int(line), stop


def modbus_node() -> None:
    """The emulated module's process: its port on stdout, served until the parent closes our stdin."""
    port, stop = modbus_in_thread()
    print(port, flush=True)
    sys.stdin.read()
    stop()


def modbus_in_thread() -> tuple[int, Any]:
    """T1 and T2 (int16, 0.01 degC) in input registers 0 and 1 of an emulated module on this process' thread."""
    from nanodrift.drivers.testing.modbus_server import ModbusTestDevice, ModbusTestServer

    logging.getLogger("pymodbus").setLevel(logging.WARNING)  # its server logs every frame at debug
    server = ModbusTestServer([ModbusTestDevice(device_id=1)])
    ready = threading.Event()
    stop: dict[str, Any] = {}

    async def serve() -> None:
        stop["loop"], stop["event"] = asyncio.get_running_loop(), asyncio.Event()
        await server.start()
        await server.set_registers(1, 0, [2180, 2190], "input")
        ready.set()
        await stop["event"].wait()
        await server.stop()

    threading.Thread(target=asyncio.run, args=(serve(),), daemon=True, name="modbus").start()
    if not ready.wait(10):
        raise SystemExit("the emulated Modbus module did not start")
    return server.port, lambda: stop["loop"].call_soon_threadsafe(stop["event"].set)


def hardware_config(cell: str, port: int, modbus_port: int, model: Path, axes: tuple[str, ...]) -> str:
    sensors = "".join(f'[[sensors]]\nname = "{name}"\nkind = "modbus"\nhub = "temps"\naddress = {address}\n'
                      'scale = 0.01\ninterval_s = 0.1\n' for address, name in enumerate(("T1", "T2")))
    if len(axes) == 1:
        actuator = '[actuator]\nkind = "zenoh"\n'
    else:
        actuator = "".join(f'[[axes]]\nname = "{a}"\nmin_um = 0.0\nmax_um = 500.0\n[axes.actuator]\nkind = "zenoh"\n'
                           for a in axes)
    return (f'cell = "{cell}"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
            f'[model]\npath = "{model}"\n{actuator}[[hubs]]\nname = "temps"\nhost = "127.0.0.1"\n'
            f"port = {modbus_port}\n{sensors}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--paced", type=int, default=3000, help="targets at 1 kHz")
    parser.add_argument("--burst", type=int, default=5000, help="targets as fast as possible")
    parser.add_argument("--idle-s", type=float, default=10.0, help="idle CPU window")
    parser.add_argument("--targets-on-loop", action="store_true",
                        help="the daemon hands each target to its asyncio loop (one more thread hop) instead of "
                             "answering on Zenoh's thread: shows why it does not")
    parser.add_argument("--axes", type=int, choices=(2, 3), default=None,
                        help="also a multi-axis cell and a one-axis cell on the same (Modbus) sensors: p50 side "
                             "by side (budget 1.2x)")
    parser.add_argument("--done-subscriber", action="store_true",
                        help="the daemons' probers also subscribe to ``done``, as nanodrift.Client does")
    parser.add_argument("--echo-node", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--modbus-node", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--daemon-on-loop", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.echo_node:
        echo_node(args.echo_node)
        return 0
    if args.modbus_node:
        modbus_node()
        return 0
    if args.daemon_on_loop:
        return daemon_on_loop(args.daemon_on_loop)

    tmp = Path(tempfile.mkdtemp(prefix="nanodrift-bench-"))
    d_port, e_port = free_port(), free_port()
    config = tmp / "bench.toml"
    config.write_text(
        f'cell = "bench"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{d_port}"]\nmulticast_scouting = false\n'
        '[simulation]\nscenario = "steady"\n'
    )
    log = tmp / "daemon.log"
    with open(log, "w") as log_file:
        command = ([sys.executable, __file__, "--daemon-on-loop", str(config)] if args.targets_on_loop
                   else [sys.executable, "-m", "nanodrift.cli", "run", "--config", str(config)])
        daemon = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=log_file, cwd=REPO)
    cells: dict[str, tuple[int, subprocess.Popen[bytes], Path, bytes]] = {}  # name -> port, process, log, template
    stop_modbus: Any = None
    if args.axes:
        axes = ("x", "y", "z")[:args.axes]
        one_model, cell_model = write_models(tmp, axes)
        modbus_port, stop_modbus = modbus_temperatures()
        template = b"{" + b", ".join(b'"%s_um": %%.3f' % a.encode() for a in axes) + b', "id": %d}'
        for name, model, cell_axes, payload in (("one-axis", one_model, ("x",), Prober.template),
                                                (f"{len(axes)}-axis", cell_model, axes, template)):
            port = free_port()
            path = tmp / f"{name}.toml"
            path.write_text(hardware_config(name, port, modbus_port, model, cell_axes))
            cell_log = tmp / f"{name}.log"
            with open(cell_log, "w") as log_file:
                cells[name] = (port, subprocess.Popen([sys.executable, "-m", "nanodrift.cli", "run", "--config",
                                                       str(path)], stdout=subprocess.DEVNULL, stderr=log_file,
                                                      cwd=REPO), cell_log, payload)
    echo = subprocess.Popen([sys.executable, __file__, "--echo-node", str(e_port)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert echo.stdout is not None
        if echo.stdout.readline().strip() != "ready":
            raise SystemExit("echo node failed to start")
        wait_line(daemon, log, '"serving"', 30)
        d = Prober(d_port, "nanodrift/bench/target", "nanodrift/bench/command", "nanodrift/bench/error",
                   "nanodrift/bench/done" if args.done_subscriber else None)
        e = Prober(e_port, ECHO_IN, ECHO_OUT)
        probers = {"echo": e, "daemon": d}
        for name, (port, process, cell_log, payload) in cells.items():
            wait_line(process, cell_log, '"serving"', 30)
            probers[name] = Prober(port, f"nanodrift/{name}/target", f"nanodrift/{name}/command",
                                   f"nanodrift/{name}/error",
                                   f"nanodrift/{name}/done" if args.done_subscriber else None)
            probers[name].template = payload
        # a daemon answers once its sensors are read: wait for the first command
        for name, prober in probers.items():
            if name == "echo":
                continue
            deadline = time.monotonic() + 20
            while not prober.run(1, 0, 10**9) and time.monotonic() < deadline:
                time.sleep(0.2)

        # paced: alternate rounds so all see the same background load on this shared machine
        paced: dict[str, list[float]] = {name: [] for name in probers}
        lost: dict[str, int] = dict.fromkeys(probers, 0)
        for prober in probers.values():
            prober.run(300, 0.001, 0)  # warm-up
        rounds = max(1, args.paced // ROUND)
        per_round = args.paced // rounds
        order = list(probers)
        for r in range(rounds):
            for name in (order if r % 2 == 0 else order[::-1]):
                times = probers[name].run(per_round, 0.001, 1_000_000 + r * per_round)
                paced[name].extend(times)
                lost[name] += per_round - len(times)
        results: dict[str, dict[str, float]] = {}
        for name, prober in probers.items():
            burst_start = time.perf_counter()
            burst = prober.run(args.burst, 0.0, 2_000_000)
            burst_s = time.perf_counter() - burst_start
            results[name] = {
                "p50_us": percentile(paced[name], 50) * 1e6,
                "p99_us": percentile(paced[name], 99) * 1e6,
                "paced_lost": lost[name],
                "burst_lost": args.burst - len(burst),
                "burst_refused": prober.errors,
                "burst_rate": len(burst) / burst_s,
            }

        cpu0, t0 = cpu_seconds(daemon.pid), time.monotonic()
        time.sleep(args.idle_s)  # measuring idle CPU: the daemon must be left alone for this window
        idle_cpu = 100.0 * (cpu_seconds(daemon.pid) - cpu0) / (time.monotonic() - t0)
        rss = rss_mb(daemon.pid)
        for prober in probers.values():
            prober.close()
    finally:
        daemon.terminate()
        daemon.wait(10)
        for _, process, _, _ in cells.values():
            process.terminate()
            process.wait(10)
        if stop_modbus is not None:
            stop_modbus()
        if echo.stdin:
            echo.stdin.close()
        echo.wait(10)

    de, dd = results["echo"], results["daemon"]
    r50, r99 = dd["p50_us"] / de["p50_us"], dd["p99_us"] / de["p99_us"]
    print(f"round trip target -> answer over tcp/127.0.0.1, {args.paced} targets at 1 kHz (alternating rounds "
          f"of {args.paced // max(1, args.paced // ROUND)}), burst of {args.burst}")
    print(f"{'':10}{'p50 us':>10}{'p99 us':>10}{'paced lost':>12}{'burst lost':>12}{'burst/s':>10}")
    for name in probers:
        row = results[name]
        print(f"{name:10}{row['p50_us']:10.1f}{row['p99_us']:10.1f}{row['paced_lost']:12.0f}{row['burst_lost']:12.0f}"
              f"{row['burst_rate']:10.0f}")
    print(f"ratio daemon/echo: p50 {r50:.2f}x (budget 1.3x), p99 {r99:.2f}x (budget 1.5x)")
    if args.targets_on_loop:
        print("(daemon variant: targets handed to the asyncio loop first, benchmarks' TargetsOnLoop)")
    print(f"daemon burst refusals: {dd['burst_refused']} (should be 0: every target was valid)")
    if args.done_subscriber:
        print("done received: " + ", ".join(f"{name} {prober.dones}" for name, prober in probers.items()
                                             if name != "echo"))
    print(f"daemon idle CPU over {args.idle_s:g} s: {idle_cpu:.1f}% of one core; RSS {rss:.1f} MB")
    within = r50 <= 1.3 and r99 <= 1.5 and dd["burst_lost"] == 0 and dd["paced_lost"] == 0
    if args.axes:
        one, many = results["one-axis"], results[f"{args.axes}-axis"]
        ratio = many["p50_us"] / one["p50_us"]
        print(f"{args.axes}-axis cell / one-axis cell (same Modbus-fed sensors, kind zenoh outputs): p50 {ratio:.2f}x "
              "(budget 1.2x)")
        within = within and ratio <= 1.2 and many["burst_lost"] == 0 and many["paced_lost"] == 0
    print("within budget" if within else "OVER BUDGET")
    return 0 if within else 1


if __name__ == "__main__":
    sys.exit(main())
