"""How the SLAP2 takes a frequency-response excitation on its wire
(``tuning.injection.Injection``): closed loop through ``ma`` targets at the maximum
profile, open loop through ``spwm`` (docs/frequency-response.md)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from servotune.devices.slap2.codec import ACCELERATION_MAX, VELOCITY_MAX
from servotune.tuning.injection import WirePlan


@dataclass(frozen=True, slots=True)
class Slap2Injection:
    """The SLAP2: a position target per step (``ma n``, ~10 characters with its echo
    and reply) and one ``rp`` sample (~16): about 26 characters, 73.8 steps/s at 19200
    baud. The maximum sv/sa for the test, so the profile generator follows the targets
    (``servotune.devices.slap2.profile`` rebuilds what it does between them)."""

    chars_per_step: int = 26
    overrides: Mapping[str, int] = field(
        default_factory=lambda: {"velocity": VELOCITY_MAX, "acceleration": ACCELERATION_MAX}
    )
    closed_loop: tuple[str, str] = ("move_absolute", "position")
    open_loop: tuple[str, str] | None = ("open_loop_pwm", "pwm")
    fault_flags: tuple[str, ...] = ("oc", "limit1", "limit2")

    def wire(self, baud: int) -> WirePlan:
        return WirePlan(baud, self.chars_per_step)

    def test_profile(self, overrides: Mapping[str, int]) -> tuple[int, int] | None:
        """The sv/sa of the test (runs recorded without overrides ran at the maximum
        this plan always sets)."""
        return (
            int(overrides.get("velocity", self.overrides["velocity"])),
            int(overrides.get("acceleration", self.overrides["acceleration"])),
        )
