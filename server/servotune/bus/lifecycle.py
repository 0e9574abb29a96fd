"""The app's one hook into the bus (``api.app`` lifespan): a rig agent or the hub side."""

from __future__ import annotations

import time
from collections.abc import Callable

from servotune.autotune.service import AutoTuner, AutoTuning
from servotune.bench.service import TestBench
from servotune.bus.autotune import HubAutoTuner
from servotune.bus.connection import BusSettings
from servotune.bus.lab_hub import HubBus
from servotune.bus.rig import RigAgent
from servotune.hub.control_client import AuditSink, ControlSettings
from servotune.hub.control_lock import ControlLock
from servotune.hub.hub import Hub
from servotune.storage import Storage


class BusLifecycle:
    """``prepare`` before the hub starts (the hub registers the rigs' links), ``start``
    once the hub and the control lock run, ``stop`` first thing at shutdown."""

    def __init__(self, settings: BusSettings) -> None:
        if (settings.rig is None) == (settings.hub is None):
            raise ValueError("the bus needs either a rig name or a hub name")
        self.settings = settings
        self.rig: RigAgent | None = None
        self.hub: HubBus | None = HubBus(settings) if settings.hub is not None else None

    async def prepare(self, hub: Hub, storage: Storage) -> None:
        if self.hub is not None:
            await self.hub.prepare(hub, storage)

    async def start(
        self,
        hub: Hub,
        control: ControlLock,
        storage: Storage,
        bench: TestBench | None = None,
        autotuner: AutoTuner | None = None,
    ) -> None:
        """``bench``: the rig's test bench, which runs the tests a hub asks for;
        ``autotuner``: the rig's auto-tune assistant, which runs a hub's auto-tune."""
        if self.hub is not None:
            await self.hub.start(control)
        else:
            self.rig = RigAgent(self.settings, hub, control, storage, bench, autotuner)
            await self.rig.start()

    async def stop(self) -> None:
        if self.rig is not None:
            await self.rig.stop()
        if self.hub is not None:
            await self.hub.stop()


def make_control(
    bus: BusSettings | None,
    hub: Hub,
    settings: ControlSettings | None = None,
    *,
    audit: Callable[[], AuditSink | None] = lambda: None,
    clock: Callable[[], float] = time.monotonic,
) -> ControlLock:
    """The control lock the app runs; at the lab hub (``servotune hub``) without the
    start-up and shutdown STOPs.

    A rig's server sent its own axes their start-up STOP when it started; the hub
    starting (or restarting, or finding a rig that joined later) must not stop an axis
    a rig's local user is driving: the hub is not on the rigs' control path for their
    local users (docs/lab.md). Every other rule holds at the hub: its tabs' locks,
    leases and lapses, whose STOPs go to the rig."""
    at_lab_hub = bus is not None and bus.hub is not None
    return ControlLock(
        hub,
        settings,
        audit=audit,
        clock=clock,
        startup_stop=not at_lab_hub,
        shutdown_stop=not at_lab_hub,
    )


def make_autotuner(bus: BusSettings | None, local: AutoTuner, hub: Hub) -> AutoTuning:
    """The auto-tune the API uses: ``local``, or at the lab hub ``local`` behind
    ``HubAutoTuner``, which forwards a rig's axis to the rig (``bus.autotune``)."""
    if bus is not None and bus.hub is not None:
        return HubAutoTuner(hub, local)
    return local
