"""The app's one hook into the bus (``api.app`` lifespan): a rig agent or the hub side."""

from __future__ import annotations

from servotune.autotune.service import AutoTuner
from servotune.bench.service import TestBench
from servotune.bus.autotune import HubAutoTuner
from servotune.bus.connection import BusSettings
from servotune.bus.lab_hub import HubBus
from servotune.bus.rig import RigAgent
from servotune.hub.control_lock import ControlManager
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
        control: ControlManager,
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


class HubControlManager(ControlManager):
    """The hub's control lock: as for local axes, except the start-up and shutdown STOPs.

    A rig's server sent its own axes their start-up STOP when it started; the hub
    starting (or restarting, or finding a rig that joined later) must not stop an axis
    a rig's local user is driving: the hub is not on the rigs' control path for their
    local users (docs/lab.md). Every other rule holds at the hub: its tabs' locks,
    leases and lapses, whose STOPs go to the rig.
    """

    startup_stop = False
    shutdown_stop = False


def control_class(settings: BusSettings | None) -> type[ControlManager]:
    """The control lock the app runs: the hub's for ``servotune hub``, else the usual."""
    if settings is not None and settings.hub is not None:
        return HubControlManager
    return ControlManager


def autotuner_class(settings: BusSettings | None) -> type[AutoTuner]:
    """The hub forwards a rig's auto-tune to the rig (``bus.autotune``)."""
    if settings is not None and settings.hub is not None:
        return HubAutoTuner
    return AutoTuner
