"""A rig's presence and clock at the hub (servotune.bus.lane.RigLiveness, bus.clock).

A presence counts from when it was *sent*, dated with the rig's clock as estimated from
round trips (never guessed from how late it seems): one that arrives older than
``offline_after_s`` is old news, whatever the reason (seen: after a 20 s outage a
rig's client delivered presences ~19 s old and the hub, taking them for a rebooted
clock, showed the rig present). Seen in CI before: a hub that showed a cut-off rig
offline took in the rig's last presence late and showed it present again. A new run
of the rig agent (another clock) counts only once a clock probe came back.
"""

from __future__ import annotations

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from servotune.bus.clock import DRIFT, RigClock
from servotune.bus.lane import RigLiveness

RIG_OFFSET_S = -4900.0  # the rig's clock against the hub's
INSTANCE = "a1b2c3d4"


def _live(now: list[float]) -> RigLiveness:
    return RigLiveness("rig-b", offline_after_s=1.5, clock=lambda: now[-1])


def _probe(live: RigLiveness, now: list[float], rtt_s: float = 0.004) -> None:
    """A clock probe sent now, answered at half its round trip."""
    sent = now[-1]
    now.append(sent + rtt_s)
    live.on_probe(sent, sent + rtt_s / 2 + RIG_OFFSET_S, INSTANCE, now[-1])


def _present_every_half_second(live: RigLiveness, now: list[float], until_s: float) -> None:
    t = now[-1]
    while t <= until_s:
        now.append(t + 0.002)  # taken in 2 ms after it was sent
        live.on_presence(t + RIG_OFFSET_S, INSTANCE, now[-1])
        t += 0.5


def test_a_presence_counts_only_once_the_rigs_clock_is_known() -> None:
    now = [100.0]
    live = _live(now)
    assert live.on_presence(100.0 + RIG_OFFSET_S, INSTANCE, 100.001) is True  # probe it
    assert not live.present()
    _probe(live, now)
    assert live.present()
    assert live.returns == 1


def test_a_presence_sent_before_the_rig_was_shown_offline_does_not_bring_it_back() -> None:
    now = [100.0]
    live = _live(now)
    _probe(live, now)
    _present_every_half_second(live, now, 104.5)
    assert live.present()
    # Cut after the presence sent at 105.0; the hub's loop is held up 1.2 s, and it
    # judges the silence (last taken in: 104.5) before it reads what came meanwhile.
    now.append(106.2)
    assert not live.present()
    live.shown_offline()
    returns = live.returns
    live.on_presence(105.0 + RIG_OFFSET_S, INSTANCE, 106.21)  # taken in 1.21 s late
    now.append(106.21)
    assert not live.present()
    assert live.returns == returns  # no snapshot asked for
    # The rig is back: its next presence is news.
    now.append(108.002)
    live.on_presence(108.0 + RIG_OFFSET_S, INSTANCE, 108.002)
    assert live.present() and live.returns == returns + 1


def test_a_late_presence_counts_from_when_it_was_sent() -> None:
    now = [100.0]
    live = _live(now)
    _probe(live, now)
    _present_every_half_second(live, now, 102.0)
    now.append(103.9)
    live.on_presence(102.5 + RIG_OFFSET_S, INSTANCE, 103.9)  # 1.4 s late: seen at 102.5
    assert live.present()
    now.append(104.1)
    assert not live.present()  # 1.6 s after it was sent


def test_presences_buffered_through_an_outage_are_old_news() -> None:
    """The rig's client buffered presences through a 20 s outage and
    delivered them at once; the hub showed the rig present on presences ~19 s old."""
    now = [100.0]
    live = _live(now)
    _probe(live, now)
    _present_every_half_second(live, now, 101.0)
    now.append(103.0)
    assert not live.present()
    live.shown_offline()
    # The lab's server is back at 121.0: the presences sent 101.5 .. 119.0 arrive now.
    t = 101.5
    while t <= 119.0:
        live.on_presence(t + RIG_OFFSET_S, INSTANCE, 121.0)
        t += 0.5
    now.append(121.0)
    assert not live.present()
    assert live.stale_presences >= 36
    # ... and the fresh ones count.
    live.on_presence(120.9 + RIG_OFFSET_S, INSTANCE, 121.0)
    assert live.present()


def test_another_run_of_the_rig_is_probed_before_its_presence_counts() -> None:
    """The rig restarted (a new agent, a new clock): its presences are not dated with
    the old clock; a probe of the new one makes it present."""
    now = [100.0]
    live = _live(now)
    _probe(live, now)
    _present_every_half_second(live, now, 102.0)
    now.append(110.0)
    assert not live.present()
    assert live.on_presence(3.0, "new-run", 110.0) is True
    assert not live.present()
    sent = now[-1]
    now.append(sent + 0.004)
    live.on_probe(sent, 3.1, "new-run", now[-1])
    assert live.present() and live.instance == "new-run"


def test_a_presence_that_cannot_be_dated_does_not_count() -> None:
    now = [100.0]
    live = _live(now)
    _probe(live, now)
    now.append(105.0)
    assert not live.present()
    assert live.on_presence(None, None, 105.0) is False
    assert not live.present()


# --- the clock estimate -----------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(
    offset=st.floats(-1e6, 1e6),
    delays=st.lists(st.tuples(st.floats(0.0, 2.0), st.floats(0.0, 2.0)), min_size=1, max_size=12),
)
def test_the_offset_interval_always_holds_the_true_offset(
    offset: float, delays: list[tuple[float, float]]
) -> None:
    """Whatever the delays each way (a held-up request, a late answer), the estimate
    brackets the true offset: it comes from round trips, not from lateness."""
    clock = RigClock()
    t = 1000.0
    for there, back in delays:
        sent = t
        rig_now = sent + there + offset
        received = sent + there + back
        assert clock.add(sent, rig_now, received)
        t = received + 0.5
    low, high = clock.bounds(t)
    assert low <= offset + 1e-6 and offset - 1e-6 <= high
    # The quickest round trip decides the width.
    fastest = min(a + b for a, b in delays)
    assert high - low <= fastest + 2 * DRIFT * (t - 1000.0) + 1e-6


def test_a_clock_that_moved_starts_the_estimate_again() -> None:
    clock = RigClock()
    assert clock.add(10.0, 5010.001, 10.002)
    assert not clock.add(20.0, 30.001, 20.002)  # another clock
    low, high = clock.bounds(20.002)
    assert low <= 10.0 <= high


def test_the_estimate_follows_a_drifting_clock() -> None:
    """A rig clock running 50 ppm fast, probed every 5 s for 10 minutes: every probe is
    consistent with the earlier ones (their intervals widen with age), and the middle
    of the interval stays within a round trip of the truth."""
    clock = RigClock()
    rng = random.Random(7)
    for k in range(120):
        sent = 100.0 + 5.0 * k
        there, back = rng.uniform(0.0005, 0.02), rng.uniform(0.0005, 0.02)
        rig_now = (sent + there) * (1 + 50e-6) - 321.0
        assert clock.add(sent, rig_now, sent + there + back)
        true_offset = rig_now - (sent + there)
        assert abs(clock.to_hub(rig_now, sent + there + back) - (sent + there)) < 0.05
        low, high = clock.bounds(sent + there + back)
        assert low - 1e-9 <= true_offset <= high + 1e-9


# --- the keep-alives say the hub can act ------------------------------------------------


class _Published:
    def __init__(self) -> None:
        self.subjects: list[str] = []

    async def publish(self, subject: str, data: bytes) -> None:
        self.subjects.append(subject)


async def test_keep_alives_are_withheld_while_the_hubs_loop_does_not_turn() -> None:
    """The lane sends keep-alives from its own thread, but only while the hub's loop
    turns: a hub whose loop hangs must let the rigs' dead-man stop what it moved."""
    import asyncio

    from servotune.bus.connection import BusSettings
    from servotune.bus.lane import MAIN_STALL_MAX_S, SafetyLane

    now = [100.0]
    lane = SafetyLane(
        BusSettings(url="nats://127.0.0.1:1", hub="lab"),
        "lab",
        lambda _: None,
        clock=lambda: now[-1],
    )
    published = _Published()
    lane._nc = published  # type: ignore[assignment]
    lane.list_rig("rig-a")
    lane.main_turned()
    task = asyncio.create_task(lane._keepalives())
    try:
        await asyncio.sleep(0.35)
        sent = len(published.subjects)
        assert sent >= 2 and set(published.subjects) == {"servotune.v1.rig-a.cmd.keepalive"}
        now.append(100.0 + MAIN_STALL_MAX_S + 0.1)  # the hub's loop stalled
        await asyncio.sleep(0.35)
        assert len(published.subjects) == sent
        assert lane.keepalives_withheld >= 2
        lane.main_turned()  # it turns again
        await asyncio.sleep(0.35)
        assert len(published.subjects) > sent
    finally:
        task.cancel()
