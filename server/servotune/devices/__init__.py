"""The devices servotune knows, one folder each, and the one list of them.

``default_registry()`` is the only place that names the devices. Its imports are inside
the function on purpose: Python runs this file on every import of any module below it,
and the simulator child processes and the compute worker import device modules without
wanting every entry (and through them the links) loaded.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from servotune.registry import Registry


def default_registry() -> Registry:
    """Every device servotune supports, in the order help texts list them; a fresh
    object per call (each composition root builds its own)."""
    from servotune.devices.ep7047.entry import ENTRY as EP7047
    from servotune.devices.slap2.entry import ENTRY as SLAP2
    from servotune.devices.z1100.entry import ENTRY as Z1100
    from servotune.registry import Registry

    return Registry((SLAP2, Z1100, EP7047))
