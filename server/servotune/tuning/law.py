"""The device-specific parts of tuning, behind one small interface per device.

Each device's folder holds its controller law (the exact integer arithmetic, tick by
tick, and its simulation on the identified plant), the identification's excitation and
its limits: ``devices/slap2/law.py`` (PID at the SLAP2 tick, open-loop PWM staircase)
and ``devices/z1100/law.py`` (K/A/B every Stm x 32 us, closed-loop move). What the
frequency response, the what-if view and the gains check need from a device (its law,
and how it takes an injected excitation: ``tuning.injection``) is ``DeviceLaw``; a
device's registry entry gives it, and generic code asks a ``DeviceLaws`` (the registry,
injected by the composition root) for it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

if TYPE_CHECKING:
    from servotune.schema import ControllerLaw
    from servotune.tuning.frf import ComplexArray, FloatArray
    from servotune.tuning.injection import Injection
    from servotune.tuning.loops import LoopModel
    from servotune.tuning.plants import IdentifiedPlant

Law = Literal["slap2_pid", "z1100_kab"]


@dataclass(frozen=True, slots=True)
class VerifyProfile:
    """The move of an auto-tune verification step, as the what-if view replays it."""

    kind: Literal["position_step", "move"]
    velocity_counts_s: float
    acceleration_counts_s2: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "velocity_counts_s": self.velocity_counts_s,
            "acceleration_counts_s2": self.acceleration_counts_s2,
        }


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
    def gain_names(self) -> tuple[str, ...]:
        """The device parameters that are the law's gains."""
        ...

    @property
    def controller(self) -> ControllerLaw:
        """The law as data (terms, divisor, rounding, gain sets): what the what-if view
        evaluates; ``tuning.loops.law_polynomials`` is its linear view."""
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

    def verify_profile(self, params: Mapping[str, int]) -> VerifyProfile:
        """The auto-tune verification's move with these device parameters."""
        ...

    def controller_response(
        self, frequency_hz: FloatArray, params: Mapping[str, int]
    ) -> ComplexArray | None:
        """The controller from the position error to the output at ``frequency_hz``,
        exact (the loop an open-loop measured plant would be closed with); None for a
        law that also acts on the position itself (no single error-to-output C).
        KeyError for a gain missing from ``params``."""
        ...


class DeviceLaws(Protocol):
    """What the bench, the what-if and the gains check need of the registry."""

    def law(self, device: str) -> DeviceLaw | None:
        """The law of ``device``; None when servotune has none for it."""
        ...
