"""Regenerate the shipped sample calibration and default model: ``python scripts/make_default_data.py [DIR]``.

``sample_calibration.csv``: a simulated 24-cycle ``train`` run (seed 0, no hidden effects), one row
per step average; ``default_model.json``: the model ``fit`` identifies from it. Both are written to
DIR (default: this repository's ``daemon/data``, the package data). Both are deterministic: running
this again reproduces them (``tests/calibration/test_validation.py`` checks it).

A maintenance script, not part of the installed package: it writes into the source tree.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from nanodrift.calibration.dataset import Dataset, read_csv, write_csv
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.model.identify import fit
from nanodrift.model.model import Model, save_model

DATA_DIR = Path(__file__).resolve().parents[1] / "daemon" / "data"
SCENARIO, SEED, CYCLES = "train", 0, 24


def sample_dataset() -> Dataset:
    return simulate_dataset(SCENARIO, cycles=CYCLES, seed=SEED, source="sample_calibration.csv")


def default_model(csv_path: Path) -> Model:
    return fit(read_csv(csv_path), source="sample_calibration.csv").model


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", nargs="?", type=Path, default=DATA_DIR,
                        help=f"where to write (default: {DATA_DIR})")
    args = parser.parse_args(argv)
    csv_path = args.dir / "sample_calibration.csv"
    write_csv(sample_dataset(), csv_path)
    model = default_model(csv_path)
    save_model(model, args.dir / "default_model.json")
    for shipped in (csv_path, args.dir / "default_model.json"):
        shipped.chmod(0o644)  # package data: readable by whoever runs the daemon
    print(f"wrote {csv_path} and {args.dir / 'default_model.json'} ({model.fit.get('residual_rms_nm', 0):.1f} nm RMS)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
