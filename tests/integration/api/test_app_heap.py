"""The app freezes the heap its start-up built (full collections skip it) and unfreezes
it at shutdown (servotune.api.app, the lifespan)."""

from __future__ import annotations

import gc
import weakref
from pathlib import Path

from servotune.api.app import AppConfig, create_app


class _Node:
    """An object in a reference cycle: only a collection that walks it frees it."""

    def __init__(self) -> None:
        self.me = self


async def test_start_up_heap_is_frozen_while_the_app_runs_and_freed_after(
    tmp_path: Path,
) -> None:
    app = create_app(AppConfig(links=[], data_dir=tmp_path / "data", web_dir=tmp_path / "w"))
    start_up = [_Node()]  # held while the app starts, like the modules and the hub
    alive = weakref.ref(start_up[0])
    gc.unfreeze()
    async with app.router.lifespan_context(app):
        assert gc.get_freeze_count() > 0
        start_up.clear()  # garbage now, but frozen: a full collection does not walk it
        gc.collect()
        assert alive() is not None
    assert gc.get_freeze_count() == 0
    gc.collect()
    assert alive() is None  # unfrozen at shutdown: nothing stays frozen past the app
