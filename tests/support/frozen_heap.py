"""Imported last by the test session's fork server (``sim_lines``): ``gc.freeze()``.

Everything the fork server imported before (the simulators, and ``compute.PRELOAD``:
numpy, scipy, pydantic) goes to the permanent generation, and the processes forked
from it inherit that: a simulator's full collection then walks only what the
simulator made, not the ~140k objects of those libraries (20-30 ms of CPU per
collection on the 2-core VM, more wall under load; docs in notes/28-i28o-import).
"""

from __future__ import annotations

import gc

gc.freeze()
