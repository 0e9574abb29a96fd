"""The device-specific parts of tuning, behind one small interface per device.

Each device module holds its controller law (the exact integer arithmetic, tick by
tick, and its simulation on the identified plant), the identification's excitation
and its limits: ``slap2`` (PID at 841.5 us, open-loop PWM staircase) and ``z1100``
(K/A/B every Stm x 32 us, closed-loop move). What the frequency response and the
what-if view need from a device (its law, and how it takes an injected excitation:
``tuning.injection``) is ``DeviceLaw``; ``law_for`` picks it. The auto-tune's
sessions (``servotune.autotune``) use the modules directly.

Layering: device modules import ``tuning.plants``, ``tuning.identify`` and
``tuning.loops``; nothing in ``tuning`` imports ``servotune.autotune``, drivers, hub
or api.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal, Protocol

from servotune.devices.slap2.law import Slap2Law
from servotune.devices.z1100.law import Z1100Law
from servotune.tuning.injection import Injection
from servotune.tuning.loops import LoopModel
from servotune.tuning.plants import IdentifiedPlant

Law = Literal["slap2_pid", "z1100_kab"]


class DeviceLaw(Protocol):
    """A device's controller law as the linear tools see it."""

    @property
    def device(self) -> str: ...

    @property
    def law(self) -> Law: ...

    @property
    def description(self) -> str:
        """The law in a few words, shown next to a model-based Bode plot."""
        ...

    @property
    def output_limit(self) -> int:
        """The controller output's full scale (PWM units)."""
        ...

    @property
    def injection(self) -> Injection | None:
        """How the device takes a frequency-response excitation on its wire
        (``tuning.injection``); None: it cannot, and its frequency response is the
        identified model's (model-based)."""
        ...

    def period_s(self, params: Mapping[str, int]) -> float:
        """The controller period with these device parameters."""
        ...

    def linear_plant(self, model: Mapping[str, Any]) -> IdentifiedPlant:
        """The linear plant of an identification (``session.model``): ValueError when
        it is not a fit of this device."""
        ...

    def loop(self, plant: IdentifiedPlant, params: Mapping[str, int]) -> LoopModel:
        """The exact discrete law with the gains in ``params`` around ``plant``
        (KeyError for a gain missing from ``params``)."""
        ...


_LAWS: dict[str, DeviceLaw] = {"slap2": Slap2Law(), "z1100": Z1100Law()}


def law_for(device: str) -> DeviceLaw:
    """The law of ``device``; ValueError when servotune has none for it."""
    try:
        return _LAWS[device]
    except KeyError:
        raise ValueError(f"no controller law for {device}") from None
