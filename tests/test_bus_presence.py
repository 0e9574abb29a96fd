"""A rig's presence at the hub (servotune.bus.remote.RemoteLink.on_presence): one the
hub takes in late is dated back by its lateness, and once the rig was shown offline,
a presence sent before that does not show it present again. Seen in CI: the hub's
loop was held up, it showed a cut-off rig offline, then took in the rig's last
presence (sent before the cut), showed it present again, and sent a parameter write
that waited 5 s for a 504 instead of being refused at once."""

from __future__ import annotations

from typing import Any

from servotune.bus.messages import RemoteLinkInfo
from servotune.bus.remote import BusPort, RemoteLink
from servotune.wire import LinkInfo

from .conftest import RecordingSink

RIG_OFFSET_S = -4900.0  # the rig machine's monotonic clock against the hub's


def _link(now: list[float]) -> RemoteLink:
    none: Any = None  # no connections: nothing here talks to the bus
    port = BusPort(
        nc=none,
        stop_nc=none,
        session="session-1",
        hub_name="hub",
        request_timeout_s=5.0,
        stop_timeout_s=1.0,
        clock=lambda: now[-1],
    )
    info = RemoteLinkInfo(
        info=LinkInfo(id="line", device="slap2", path="/dev/ttyUSB0", baud=19200), axes=[]
    )
    return RemoteLink("rig-b", info, port, RecordingSink(), offline_after_s=1.5)


def _present_every_half_second(link: RemoteLink, now: list[float], until_s: float) -> None:
    t = now[-1]
    while t <= until_s:
        now.append(t + 0.002)  # taken in 2 ms after it was sent
        link.on_presence(t + RIG_OFFSET_S)
        t += 0.5


def test_a_presence_sent_before_the_rig_was_shown_offline_does_not_bring_it_back() -> None:
    now = [100.0]
    link = _link(now)
    _present_every_half_second(link, now, 104.5)
    assert link.present()
    # Cut after the presence sent at 105.0; the hub's loop is held up 1.2 s, and it
    # judges the silence (last taken in: 104.5) before it reads what came meanwhile.
    now.append(106.2)
    assert not link.present()
    link.show_offline("rig rig-b is offline (no presence for 1.7 s)")
    link.snapshot_wanted.clear()
    now.append(106.21)
    link.on_presence(105.0 + RIG_OFFSET_S)  # sent at 105.0, taken in 1.21 s late
    assert not link.present()
    assert not link.snapshot_wanted.is_set()
    # The rig is back: its next presence is news.
    now.append(108.002)
    link.on_presence(108.0 + RIG_OFFSET_S)
    assert link.present() and link.snapshot_wanted.is_set()


def test_a_late_presence_counts_from_when_it_was_sent() -> None:
    now = [100.0]
    link = _link(now)
    _present_every_half_second(link, now, 102.0)
    now.append(103.9)
    link.on_presence(102.5 + RIG_OFFSET_S)  # 1.4 s late: seen at 102.5, not 103.9
    assert link.present()
    now.append(104.1)
    assert not link.present()  # 1.6 s after it was sent


def test_another_clock_is_not_taken_for_lateness() -> None:
    """The rig's machine rebooted (its monotonic clock started again): presences are
    counted as they come, not as 'thousands of seconds late'."""
    now = [100.0]
    link = _link(now)
    _present_every_half_second(link, now, 102.0)
    now.append(110.0)
    link.on_presence(3.0)  # a fresh clock
    assert link.present()


def test_a_presence_without_the_rig_clock_counts_when_it_came() -> None:
    now = [100.0]
    link = _link(now)
    link.on_presence()
    now.append(101.4)
    assert link.present()
    now.append(101.6)
    assert not link.present()
