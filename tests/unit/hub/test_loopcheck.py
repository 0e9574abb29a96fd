"""The loop check (servotune.hub.loopcheck) on synthetic telemetry: what is a loop that
does not work, and what is one that works hard."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import pytest
from hypothesis import given
from hypothesis import strategies as st

from servotune.descriptor import LoopSignals
from servotune.devices import default_registry
from servotune.hub import loopcheck
from servotune.link.base import Sample

# The devices' controller laws, looked up as the app does.
LAW = default_registry().law

SIGNALS = LoopSignals(
    position_channel="position",
    following_error_channel="following_error",
    current_limit_flag="oc",
    closed_loop_flags=["pm", "vm"],
    oscillation_counts=100,
    rest_velocity=200,
)


def samples(
    seconds: float,
    rate_hz: float,
    setpoint: Callable[[float], float],
    error: Callable[[float], float],
    *,
    pm: bool = True,
    oc: Callable[[float], bool] = lambda t: False,
) -> list[Sample]:
    out = []
    for i in range(int(seconds * rate_hz)):
        t = i / rate_hz
        e = round(error(t))
        out.append(
            Sample(
                t=t,
                channels={"position": setpoint(t) - e, "following_error": e},
                flags={"pm": pm, "vm": False, "oc": oc(t)},
            )
        )
    return out


def judge(data: list[Sample]) -> loopcheck.LoopVerdict:
    return loopcheck.judge(data, SIGNALS, since=data[0].t)


@pytest.mark.parametrize("rate_hz", [25.6, 68.0, 160.0])
def test_a_limit_cycle_around_a_held_position_is_an_oscillation(rate_hz: float) -> None:
    # The loaded demo SLAP2 with its factory gains after a position step: ±1900 at ~10
    # Hz, the setpoint held. Seen at the polled rate of a two-module line (25.6 Hz), a
    # one-module line and a capture.
    data = samples(1.5, rate_hz, lambda t: 500.0, lambda t: 1900 * math.sin(2 * math.pi * 9.7 * t))
    verdict = judge(data)
    assert verdict.working is False and verdict.fault == "oscillation", verdict
    assert "±" in verdict.reason


def test_ringing_that_dies_out_is_a_working_loop() -> None:
    ring = samples(
        1.0, 160, lambda t: 2000.0, lambda t: 600 * math.exp(-t / 0.08) * math.cos(60 * t)
    )
    assert judge(ring).working is True


def test_following_a_multisine_or_a_jog_is_not_an_oscillation() -> None:
    multisine = samples(
        2.0,
        160,
        lambda t: 200 * math.sin(2 * math.pi * 5 * t) + 150 * math.sin(2 * math.pi * 9 * t),
        lambda t: 60 * math.sin(2 * math.pi * 5 * t + 1) + 80 * math.sin(2 * math.pi * 9 * t),
    )
    assert judge(multisine).working is True
    jog = samples(
        3.0,
        25.6,
        lambda t: 3000 * math.sin(2 * math.pi * 1.5 * t),
        lambda t: 400 * math.cos(2 * math.pi * 1.5 * t),
    )
    assert judge(jog).working is True


def test_a_runaway_is_diverging_and_a_fast_moves_transient_is_not() -> None:
    runaway = samples(1.0, 25.6, lambda t: 0.0, lambda t: 6000 * t)
    verdict = judge(runaway)
    assert verdict.working is False and verdict.fault == "diverging", verdict
    # A position step: the error builds up for 0.15 s while the profile outruns the
    # motor, then turns back.
    step = samples(
        1.0,
        160,
        lambda t: min(t, 0.15) * 40000,
        lambda t: 3000 * min(t, 0.15) / 0.15 * math.exp(-max(0.0, t - 0.15) / 0.05),
    )
    assert judge(step).working is True


def test_a_current_limit_held_is_a_fault_a_short_one_is_not() -> None:
    held = samples(1.0, 25.6, lambda t: 0.0, lambda t: 30.0, oc=lambda t: t > 0.4)
    verdict = judge(held)
    assert verdict.working is False and verdict.fault == "current_limit", verdict
    brief = samples(1.0, 25.6, lambda t: 0.0, lambda t: 30.0, oc=lambda t: 0.4 < t < 0.6)
    assert judge(brief).working is True


def test_no_evidence_with_the_loop_off_or_too_few_samples() -> None:
    off = samples(1.5, 25.6, lambda t: 0.0, lambda t: 1900 * math.sin(60 * t), pm=False)
    assert judge(off) == loopcheck.NO_EVIDENCE
    few = samples(1.5, 25.6, lambda t: 0.0, lambda t: 0.0)[:2]
    assert judge(few).working is None
    assert loopcheck.judge(few, SIGNALS, since=few[0].t - 1.0).sparse  # 1 s unseen


def test_at_rest() -> None:
    still = samples(0.5, 25.6, lambda t: 100.0, lambda t: 3.0)
    assert loopcheck.at_rest(still, SIGNALS, since=0.0)
    creeping = samples(0.5, 25.6, lambda t: 100.0 + 50 * t, lambda t: 3.0)  # 50 counts/s
    assert loopcheck.at_rest(creeping, SIGNALS, since=0.0)
    moving = samples(0.5, 25.6, lambda t: 100.0 + 5000 * t, lambda t: 3.0)
    assert not loopcheck.at_rest(moving, SIGNALS, since=0.0)
    pulling = samples(0.5, 25.6, lambda t: 100.0, lambda t: 400.0)  # held far off target
    assert not loopcheck.at_rest(pulling, SIGNALS, since=0.0)
    assert not loopcheck.at_rest(still[:3], SIGNALS, since=0.0)  # too short to say


@given(st.lists(st.floats(-1e6, 1e6), max_size=60), st.floats(1, 1e4))
def test_swings_are_confirmed_extremes_at_least_the_hysteresis_apart(
    values: list[float], hysteresis: float
) -> None:
    extremes = loopcheck.swings(values, hysteresis)
    indices = [i for i, _ in extremes]
    assert indices == sorted(indices) and len(set(indices)) == len(indices)
    for (_, a), (_, b) in itertools.pairwise(extremes):
        assert abs(b - a) >= hysteresis
    # Successive extremes alternate: a maximum, then a minimum, ...
    for (_, a), (_, b), (_, c) in zip(extremes, extremes[1:], extremes[2:], strict=False):
        assert (b - a) * (c - b) < 0


def test_swings_of_noise_below_the_hysteresis_are_none() -> None:
    assert loopcheck.swings([0, 40, -40, 30, -30, 0], 100) == []
    assert loopcheck.swings([0, 200, 0, 200, 0], 100) == [(0, 0), (1, 200), (2, 0), (3, 200)]


def test_a_limit_cycle_on_top_of_a_constant_velocity_is_an_oscillation() -> None:
    # Velocity mode at 187 000 counts/s with gains that oscillate there: the setpoint
    # moves on steadily, the error swings.
    data = samples(
        1.5, 25.6, lambda t: 187000 * t, lambda t: 1500 * math.sin(2 * math.pi * 7.3 * t)
    )
    verdict = judge(data)
    assert verdict.working is False and verdict.fault == "oscillation", verdict


def test_only_the_newest_stretch_with_the_loop_on_is_judged() -> None:
    # A limit cycle that was switched off (st), then a quiet hold: not judged from the
    # part before the loop went off.
    before = samples(1.0, 25.6, lambda t: 0.0, lambda t: 1900 * math.sin(60 * t))
    off = [
        Sample(1.0 + i / 25.6, {"position": 0, "following_error": 0}, {"pm": False})
        for i in range(3)
    ]
    quiet = [
        Sample(1.2 + i / 25.6, {"position": 0, "following_error": 2}, {"pm": True})
        for i in range(20)
    ]
    assert judge([*before, *off, *quiet]).working is True
    assert judge([*before, *off]) == loopcheck.NO_EVIDENCE
    # A loop switched on 0.35 s ago has not shown yet that it works; densely sampled,
    # nothing says a swing was missed: not judged yet, not "too sparse".
    short = judge([*before, *off, *quiet[:10]])
    assert short.working is None and not short.sparse and "0.35 s" in short.reason, short


# --- evidence: the samples' own timestamps, not their count ---------------------------

# The loaded demo SLAP2's limit cycle (factory gains, ±1 960 counts around a held
# setpoint of 2 000) as a starved host polled it at ~13 samples/s: recorded from the
# stop rig at load ~8 (time from the newest sample, following error). Aliased, its
# swings scatter and the newer ones look smaller: the check had called it "working".
ALIASED_LIMIT_CYCLE = [
    (-1.498, -1965), (-1.399, -933), (-1.328, -1909), (-1.267, -404), (-1.197, 1404),
    (-1.125, 1969), (-1.049, 1764), (-0.971, 1356), (-0.904, -828), (-0.843, -1759),
    (-0.787, 1625), (-0.715, 1970), (-0.650, 18), (-0.577, -1227), (-0.492, -933),
    (-0.406, -485), (-0.338, -1877), (-0.264, -1903), (-0.189, -1248), (-0.091, -1953),
    (0.000, -1227),
]  # fmt: skip


def held(points: list[tuple[float, float]], setpoint: float = 2000.0) -> list[Sample]:
    return [
        Sample(
            t=t,
            channels={"position": setpoint - e, "following_error": e, "setpoint": setpoint},
            flags={"pm": True, "vm": False, "move": False, "oc": False},
        )
        for t, e in points
    ]


SLAP2 = SIGNALS.model_copy(update={"moving_flags": ["move", "vm"], "reference_channel": "setpoint"})


def test_a_limit_cycle_sampled_about_as_fast_as_it_swings_is_never_called_working() -> None:
    verdict = loopcheck.judge(held(ALIASED_LIMIT_CYCLE), SLAP2, since=-1.5)
    assert verdict.working is not True, verdict
    assert verdict.working is False or verdict.sparse, verdict


def sparse_limit_cycle(gaps_s: list[float], hz: float = 9.7) -> list[Sample]:
    t, points = -sum(gaps_s), []
    for gap in [0.0, *gaps_s]:
        t += gap
        points.append((t, 1900 * math.sin(2 * math.pi * hz * t)))
    return held(points)


@pytest.mark.parametrize(
    "gaps_s",
    [
        [0.3, 0.25, 0.35, 0.3, 0.3],  # a starved host: ~3 samples/s
        [0.05] * 6 + [0.45] + [0.05] * 4,  # one long stall in the window
    ],
    ids=["slow-polls", "one-stall"],
)
def test_sparse_telemetry_is_no_evidence_that_the_loop_works(gaps_s: list[float]) -> None:
    data = sparse_limit_cycle(gaps_s)
    verdict = loopcheck.judge(data, SLAP2, since=data[-1].t - 1.5)
    assert verdict.working is not True and verdict.sparse, verdict
    assert "telemetry too sparse" in verdict.reason


def test_late_telemetry_is_no_evidence_of_now() -> None:
    # A loop that works, densely sampled - but the newest sample is 0.4 s old.
    data = held([(-1.5 + i / 25.6, 3.0) for i in range(39)])
    assert loopcheck.judge(data, SLAP2, since=-1.5).working is True
    late = loopcheck.judge(data, SLAP2, since=-1.5, age_s=0.4)
    assert late.working is None and late.sparse and "0.40 s" in late.reason, late


HELD = SIGNALS.model_copy(update={"moving_flags": ["move", "vm"]})


def test_an_aliased_oscillation_of_a_held_position_is_seen_in_the_position() -> None:
    # Seen on the simulated Z1100 (Stm 16, K 255): a ~50 Hz limit cycle sampled at 12 Hz;
    # the error is read at another moment than the position, so it scatters around an
    # offset, and position + error (the derived setpoint) scatters with it.
    data = [
        Sample(
            t=i / 12.0,
            channels={
                "position": 20240 + 215 * math.sin(2 * math.pi * 43.1 * i / 12.0),
                "following_error": 520 + 210 * math.sin(2 * math.pi * 43.1 * i / 12.0 + 2.0),
            },
            flags={"pm": True, "move": False},
        )
        for i in range(18)
    ]
    verdict = loopcheck.judge(data, HELD, since=0.0)
    assert verdict.working is False and verdict.fault == "oscillation", verdict
    assert "held" in verdict.reason
    # Without knowing the reference is held, the scattering sum looks like a moving one.
    assert loopcheck.judge(data, SIGNALS, since=0.0).working is True


def test_a_stop_that_overshoots_once_and_settles_is_not_an_oscillation() -> None:
    # The loaded module held at 187 000 counts/s: ~1 200 counts over, then back.
    data = samples(
        1.0,
        25.6,
        lambda t: 0.0,
        lambda t: -1200 * math.exp(-t / 0.03) * math.cos(2 * math.pi * 3 * t),
    )
    for sample in data:
        sample.flags["move"] = False  # type: ignore[index]
    assert loopcheck.judge(data, HELD, since=0.0).working is True


# --- gains predicted unstable on an identified plant (servotune.tuning.predicted) ---------

SLAP2_MODEL = {"gain_counts_s_per_pwm": 998.0, "tau_s": 0.012}  # the demo's unloaded module


@pytest.mark.parametrize(
    ("gains", "unstable"),
    [
        ({"kp": 40, "ki": 40, "kd": 80}, False),  # the manual's defaults
        ({"kp": 1676, "ki": 0, "kd": 1100}, False),  # an auto-tune proposal (ki 0)
        ({"kp": 1, "ki": 0, "kd": 0}, False),  # slow, but it settles
        ({"kp": 2000, "ki": 0, "kd": 0}, True),  # no damping: it rings up
        ({"kp": 32767, "ki": 32767, "kd": 0}, True),
    ],
)
def test_gains_predicted_unstable_on_the_identified_plant(
    gains: dict[str, int], unstable: bool
) -> None:
    from servotune.tuning.predicted import unstable_reason

    assert bool(unstable_reason(LAW("slap2"), SLAP2_MODEL, gains)) is unstable
