"""What a device's wire allows a frequency-response injection to measure (sans-IO).

A device that takes its excitation over a serial line gets one injection step (a new
target, and a sample of the response) per round trip of a few short commands. The
line's character rate bounds the steps per second; the samples come at that rate at
best, and the capture's Nyquist frequency bounds the tones worth sending: a tone
above it is aliased, and the samples cannot tell its response from a lower tone's.

``WirePlan`` turns a baud rate and the characters of one step into the expected
sample rate and the highest tone placed (``max_tone_hz``); ``split`` divides a
requested band into the part measured and the tones left out, with the reason the
API shows (``not_measured_hz``, ``not_measured_reason``).

A device that can inject implements ``Injection`` (``tuning.law.DeviceLaw.injection``;
the SLAP2's is ``devices/slap2/injection.py``). A device without one (Z1100: no target
or PWM can be streamed on its wire without leaving its own profile) gets a model-based
frequency response instead.

Nothing here imports drivers, hub or api (``servotune.bench.frf`` builds the bench's
plan from this).
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping
from dataclasses import dataclass
from typing import Any, Final, Protocol

BITS_PER_CHAR: Final = 10  # start + 8 data + stop
# Injection runs sample below the characters' limit (the host's turnaround between
# commands, the status read after a refused-or-not check, gaps when the host is
# loaded; docs/frequency-response.md has the measured share): plan with 70 %.
EXPECTED_FRACTION: Final = 0.7
# Tones up to 80 % of the expected Nyquist frequency: a run that gets somewhat fewer
# samples than expected still resolves every tone it sent.
TONE_FRACTION: Final = 0.8


@dataclass(frozen=True, slots=True)
class WirePlan:
    """The pace of an injection over a serial line: ``chars_per_step`` characters (both
    directions, echoes included) per target sent and sample read, at ``baud``."""

    baud: int
    chars_per_step: int

    @property
    def steps_per_s_limit(self) -> float:
        """Steps per second if the line carried nothing else and never paused."""
        return self.baud / BITS_PER_CHAR / self.chars_per_step

    @property
    def expected_rate_hz(self) -> float:
        """The sample rate to plan with (``EXPECTED_FRACTION`` of the limit)."""
        return EXPECTED_FRACTION * self.steps_per_s_limit

    @property
    def nyquist_hz(self) -> float:
        return self.expected_rate_hz / 2.0

    @property
    def max_tone_hz(self) -> float:
        """The highest tone an injection on this wire sends."""
        return TONE_FRACTION * self.nyquist_hz

    def reason(self) -> str:
        return (
            f"above what the wire resolves: at {self.baud} baud one injection step "
            f"({self.chars_per_step} characters) allows {self.steps_per_s_limit:.1f} "
            f"samples/s, about {self.expected_rate_hz:.0f}/s expected (Nyquist "
            f"{self.nyquist_hz:.1f} Hz); tones are sent up to {self.max_tone_hz:.1f} Hz"
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "baud": self.baud,
            "chars_per_step": self.chars_per_step,
            "steps_per_s_limit": round(self.steps_per_s_limit, 2),
            "expected_rate_hz": round(self.expected_rate_hz, 2),
            "nyquist_hz": round(self.nyquist_hz, 2),
            "max_tone_hz": round(self.max_tone_hz, 2),
        }


class Injection(Protocol):
    """How a device takes a frequency-response excitation on its wire."""

    @property
    def chars_per_step(self) -> int:
        """Characters on the line per injection step (a target and a sample)."""
        ...

    @property
    def overrides(self) -> Mapping[str, int]:
        """Device parameters set for a closed-loop test and restored after it."""
        ...

    @property
    def closed_loop(self) -> tuple[str, str]:
        """(command, argument) each closed-loop target is sent as."""
        ...

    @property
    def open_loop(self) -> tuple[str, str] | None:
        """(command, argument) of an open-loop drive value; None: no open loop."""
        ...

    @property
    def fault_flags(self) -> tuple[str, ...]:
        """Status flags that end the test."""
        ...

    def wire(self, baud: int) -> WirePlan: ...

    @property
    def tick_s(self) -> float:
        """The controller's tick: the grid the loop's input is rebuilt on."""
        ...

    def input_model(self, overrides: Mapping[str, int]) -> InputModel:
        """How the loop's input followed the targets of a closed-loop test run with
        the plan's ``overrides`` (empty for a run recorded without them)."""
        ...


class SetpointGenerator(Protocol):
    """The loop's input on the controller's tick grid, replayed from the targets."""

    def retarget(self, target: float) -> None:
        """A target the device latched before the next tick."""
        ...

    def step(self) -> float:
        """One tick; the input after it."""
        ...

    def state(self) -> Hashable:
        """Everything the following ticks depend on (equal states: equal futures)."""
        ...


class InputModel(Protocol):
    """How a device's loop input follows the targets of an injection
    (``tuning.frfrun.rebuild_input``)."""

    @property
    def tick_s(self) -> float: ...

    @property
    def name(self) -> str:
        """What the input is, for the analysis' ``input`` field: "profile" (a setpoint
        generator between the targets) or "targets" (each target held)."""
        ...

    def start(self, y0: float) -> SetpointGenerator:
        """At rest at ``y0``."""
        ...

    def resume(self, state: Hashable) -> SetpointGenerator:
        """From a ``SetpointGenerator.state()``."""
        ...


@dataclass(frozen=True, slots=True)
class HeldTargets:
    """The input jumps to each target at the first tick after it latched and holds it
    (a setpoint without a profile generator; an open-loop PWM)."""

    tick_s: float
    name: str = "targets"

    def start(self, y0: float) -> SetpointGenerator:
        return _Held(y0)

    def resume(self, state: Hashable) -> SetpointGenerator:
        assert isinstance(state, float)
        return _Held(state)


class _Held:
    __slots__ = ("value",)

    def __init__(self, value: float) -> None:
        self.value = float(value)

    def retarget(self, target: float) -> None:
        self.value = float(target)

    def step(self) -> float:
        return self.value

    def state(self) -> Hashable:
        return self.value


def split(
    wire: WirePlan, low_hz: float, high_hz: float, requested_tones_hz: tuple[float, ...]
) -> tuple[float, tuple[float, ...]]:
    """The top of the band measured on ``wire`` (``high_hz`` or ``max_tone_hz``) and the
    requested tones above it (``requested_tones_hz``: the excitation the whole band
    would have had). ValueError when even ``low_hz`` lies above what the wire resolves
    (the caller answers 422 naming low_hz)."""
    top = wire.max_tone_hz
    if low_hz > top:
        raise ValueError(f"low_hz {low_hz:g} Hz is {wire.reason()}: ask for low_hz <= {top:.1f} Hz")
    if high_hz <= top:
        return high_hz, ()
    return top, tuple(f for f in requested_tones_hz if f > top)
