"""How the SLAP2 takes a frequency-response excitation on its wire
(``tuning.injection.Injection``): closed loop through ``ma`` targets at the maximum
profile, open loop through ``spwm`` (docs/frequency-response.md)."""

from __future__ import annotations

from collections.abc import Hashable, Mapping
from dataclasses import dataclass, field

from servotune.devices.slap2.codec import ACCELERATION_MAX, TICK_S, VELOCITY_MAX
from servotune.devices.slap2.profile import TrapezoidGenerator
from servotune.tuning.injection import InputModel, SetpointGenerator, WirePlan


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

    @property
    def tick_s(self) -> float:
        return TICK_S

    def input_model(self, overrides: Mapping[str, int]) -> InputModel:
        """The firmware's trapezoid at the test's sv/sa (runs recorded without
        overrides ran at the maximum this plan always sets)."""
        return TrapezoidInput(
            int(overrides.get("velocity", self.overrides["velocity"])),
            int(overrides.get("acceleration", self.overrides["acceleration"])),
        )


@dataclass(frozen=True, slots=True)
class TrapezoidInput:
    """The SLAP2's setpoint between the targets: the firmware's profile generator
    (``devices/slap2/profile.py``) at ``sv``/``sa`` (wire units). At the maximum sv/sa
    a 50-count jump still takes about 10 ticks (8 ms), a delay the response must not
    be blamed for."""

    sv: int
    sa: int
    tick_s: float = TICK_S
    name: str = "profile"

    def start(self, y0: float) -> SetpointGenerator:
        return _Trapezoid(TrapezoidGenerator(y0, y0, 1.0, 1.0, 0.0, False), self.sv, self.sa)

    def resume(self, state: Hashable) -> SetpointGenerator:
        assert isinstance(state, tuple)
        return _Trapezoid(TrapezoidGenerator(*state), self.sv, self.sa)


class _Trapezoid:
    __slots__ = ("generator", "sa", "step", "sv")

    def __init__(self, generator: TrapezoidGenerator, sv: int, sa: int) -> None:
        self.generator, self.sv, self.sa = generator, sv, sa
        self.step = generator.step  # called once per tick: no extra call

    def retarget(self, target: float) -> None:
        self.generator.replan(target, self.sv, self.sa)

    def state(self) -> Hashable:
        g = self.generator
        return (g.setpoint, g.target, g.vmax, g.acceleration, g.velocity, g.moving)
