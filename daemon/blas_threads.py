"""One BLAS thread for the command line and the daemon, unless the environment says otherwise.

nanodrift's linear algebra is on small matrices (a stepwise fit's QR of a few hundred rows by a dozen
columns, 8x8 triangular solves). OpenBLAS's threads only cost there, and on a loaded two-core lab PC they
spin against the daemon and each other: an 8x8 triangular solve took 2.4 ms with OpenBLAS's default
threads beside other work, 13 µs with one (a QR of 300x10: 14 ms and 1.3 ms). Imported by ``nanodrift.cli``
before anything imports numpy; a variable already set (``OPENBLAS_NUM_THREADS=4 nanodrift fit ...``) wins.
A library user's own process is left as it is.
"""

from __future__ import annotations

import os

THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

for _name in THREAD_VARIABLES:
    os.environ.setdefault(_name, "1")
