"""One BLAS thread in a process that does the tuning's linear algebra (imported first).

The fits are small (hundreds of rows, tens of columns): threads gain nothing there,
and on a loaded 2-core host OpenBLAS's threads spin against each other and against
the event loop (docs/architecture.md, "Heavy work", has the measurement). Effective only
when imported before numpy (the compute worker's fork server imports it first,
``servotune.compute.PRELOAD``); a value already set in the environment is kept.
"""

from __future__ import annotations

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
