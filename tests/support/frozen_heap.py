"""Imported last by the test session's fork server (``sim_lines``): ``gc.freeze()``.

Everything the fork server imported before (the simulators, and ``compute.PRELOAD``:
numpy, scipy, pydantic) goes to the permanent generation, and the processes forked
from it inherit that: a simulator's full collection then walks only what the
simulator made, not the objects of those libraries, which it never frees.
"""

from __future__ import annotations

import gc

gc.freeze()
