"""A facility on this machine: status latency and per-cell target latency with 1, 5 and 20 cells.

Each fleet is N simulated cells (``nanodrift run``, each its own process, run light: three
temperature channels polled once a second) behind one Zenoh router (a session in router mode in this
process) on 127.0.0.1, under the prefix ``site/hall2``, with user/password authentication and the
access control ``nanodrift acl`` writes (``--no-acl``: an open router). The client is group ``a``'s
user, allowed to move every cell. Per fleet:

- start: from launching the daemons to every cell's ``alive`` token at the router;
- status: one ``Client.statuses()`` (what ``nanodrift status`` does: a query on ``site/hall2/*/status``
  answered by every cell), repeated; the answer must list all N;
- target: ``Client.move()`` (target -> command -> done ``reached``), round trip, on every cell in turn.

Ratios are against the 1-cell fleet of the same run.

    .venv/bin/python benchmarks/fleet.py [--sizes 1,5,20] [--status-rounds 30] [--moves 10] [--no-acl]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test helpers ...
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # ... after the repo: tests/drivers is not drivers

from helpers.fleet import PREFIX, Fleet, cell_name

from nanodrift import Client


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def measure(size: int, root: Path, status_rounds: int, moves: int, acl: bool) -> dict[str, float]:
    names = [cell_name(i) for i in range(size)]
    groups = {"a": (["alice"], names), "watch": (["grafana"], [])} if acl else None
    fleet = Fleet(root, size, groups=groups)
    began = time.monotonic()
    fleet.start(timeout_s=180.0)
    start_s = time.monotonic() - began
    config = fleet.user_configs.get("alice")
    try:
        with Client(fleet.endpoint, None, prefix=PREFIX, zenoh_config=config) as network:
            status_s = []
            for _ in range(status_rounds):
                t0 = time.perf_counter()
                docs = network.statuses(timeout_s=5.0)
                status_s.append(time.perf_counter() - t0)
                assert len(docs) == size, f"status listed {len(docs)} of {size} cells"
        move_s = []
        for name in names:
            with Client(fleet.endpoint, name, prefix=PREFIX, zenoh_config=config) as cell:
                cell.move(100.0)  # routes in place
                for index in range(moves):
                    t0 = time.perf_counter()
                    cell.move(100.0 + 10.0 * (index % 5))
                    move_s.append(time.perf_counter() - t0)
    finally:
        codes = fleet.close()
    assert set(codes.values()) == {0}, codes
    return {"start_s": start_s, "status_p50_ms": 1e3 * statistics.median(status_s),
            "status_max_ms": 1e3 * max(status_s), "move_p50_ms": 1e3 * statistics.median(move_s),
            "move_p99_ms": 1e3 * percentile(move_s, 0.99), "moves": len(move_s)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1,5,20", help="fleet sizes, comma-separated")
    parser.add_argument("--status-rounds", type=int, default=30)
    parser.add_argument("--moves", type=int, default=10, help="moves per cell")
    parser.add_argument("--no-acl", action="store_true", help="an open router (no authentication, no ACL)")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    results = {}
    with tempfile.TemporaryDirectory(prefix="nanodrift-fleet-") as tmp:
        for size in sizes:
            results[size] = measure(size, Path(tmp) / f"fleet{size}", args.status_rounds, args.moves, not args.no_acl)
            print(f"{size} cells measured", file=sys.stderr)
    base = results[sizes[0]]
    print(f"fleet behind one router, prefix {PREFIX}, {'ACL + authentication' if not args.no_acl else 'open router'}")
    print(f"{'cells':>5} {'start s':>8} {'status p50 ms':>14} {'status max ms':>14} {'move p50 ms':>12} "
          f"{'move p99 ms':>12} {'status x':>9} {'move x':>7}")
    for size, r in results.items():
        print(f"{size:>5} {r['start_s']:>8.1f} {r['status_p50_ms']:>14.1f} {r['status_max_ms']:>14.1f} "
              f"{r['move_p50_ms']:>12.2f} {r['move_p99_ms']:>12.2f} {r['status_p50_ms'] / base['status_p50_ms']:>9.2f} "
              f"{r['move_p50_ms'] / base['move_p50_ms']:>7.2f}")
    print(f"(x: ratio to the {sizes[0]}-cell fleet; moves: target -> command -> done reached, "
          f"{args.moves} per cell; status: all cells answered)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
