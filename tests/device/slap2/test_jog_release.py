"""SLAP2 jog release planning (``Slap2Axis.jog_stop_target``), pure: the release's ``ma``
target is ahead of the shaft in the jog's direction whatever the reconstructed profile's
latch stamp says, and never further than braking with sa from the true state allows."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pytest

from servotune.devices.slap2 import codec
from servotune.devices.slap2.axis import JOG_TARGET, Slap2Axis
from servotune.devices.slap2.profile import ProfileTrack, TrapezoidGenerator

SV, SA = 3000, 500  # the demo jog's settings (wire units)
NOW_S = 2.0  # host time of the release


@dataclass
class _Profile:
    track: ProfileTrack | None


@dataclass
class _Module:
    """The fields of the link's module state the release reads."""

    profile: _Profile
    rss: int
    position: int
    position_t: float
    following_error: int
    velocity: float  # counts/s, measured
    known: dict[str, int] = field(default_factory=lambda: {"velocity": SV, "acceleration": SA})


class _Link:
    def __init__(self, module: _Module) -> None:
        self.module = module

    def module_state(self, address: int) -> Any:
        return self.module

    def now(self) -> float:
        return NOW_S


def _jog_track(t_command_s: float, direction: int) -> ProfileTrack:
    return ProfileTrack(
        t_command_s, TrapezoidGenerator.from_wire(0.0, direction * JOG_TARGET, SV, SA)
    )


def _axis(
    recorded_start_s: float, direction: int, poll_age_s: float
) -> tuple[Slap2Axis, ProfileTrack]:
    """An axis jogging in ``direction`` since t = 0 (the truth); the link's reconstructed
    profile says it started at ``recorded_start_s``; the last poll, ``poll_age_s`` old,
    saw the true state."""
    true = _jog_track(0.0, direction)
    poll_t = NOW_S - poll_age_s
    state = true.state_at(poll_t)
    module = _Module(
        profile=_Profile(_jog_track(recorded_start_s, direction)),
        rss=codec.encode_bits({"pm": True, "move": True}, codec.RssBit),
        position=round(true.setpoint_at(poll_t)),
        position_t=poll_t,
        following_error=0,
        velocity=abs(state.velocity) / codec.TICK_S,
    )
    axis = Slap2Axis(_Link(module), 0)  # type: ignore[arg-type]
    axis._jog_direction = direction  # a jog of ours runs (what _jog sets)
    return axis, true


def _true_rest(true: ProfileTrack, direction: int) -> float:
    """Where the true jog would come to rest braking with sa from now."""
    state = true.state_at(NOW_S)
    v = abs(state.velocity)
    return true.setpoint_at(NOW_S) + direction * v * v / (2 * state.acceleration)


@pytest.mark.parametrize("direction", [1, -1])
@pytest.mark.parametrize("latch_late_s", [0.0, 0.3, 0.6])
def test_the_release_stops_ahead_of_the_shaft_even_from_a_late_latch_stamp(
    direction: int, latch_late_s: float
) -> None:
    axis, true = _axis(latch_late_s, direction, poll_age_s=0.02)
    target = axis.jog_stop_target(NOW_S)
    assert target is not None
    shaft = true.setpoint_at(NOW_S)
    rest = _true_rest(true, direction)
    # Ahead of the shaft (no return), within 5 % of the braking distance of the truth.
    assert (target - shaft) * direction > 0, (target, shaft)
    assert abs(target - rest) <= 0.05 * abs(rest - shaft), (target, rest, shaft)


def test_a_move_that_is_not_a_jog_of_ours_keeps_its_profile() -> None:
    """A move typed in the console: no jog direction, so the profile alone decides."""
    axis, _ = _axis(0.0, 1, poll_age_s=0.02)
    axis._jog_direction = 0
    track = axis._link.module_state(0).profile.track  # type: ignore[attr-defined]
    state = track.state_at(NOW_S + 0.012)
    target = axis.jog_stop_target(NOW_S)
    assert target is not None and target > state.setpoint
