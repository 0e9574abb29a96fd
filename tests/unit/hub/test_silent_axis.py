"""The hub's judgement of an axis that sends no telemetry while its link is up
(servotune.hub.state.HubState, AXIS_SILENT_S): shown offline - it has no live values -
and, when its link says the host itself held the bytes back (its ``host_stalls``
counter grew), the message blames the host, not the device. Clock injected; the status
tick is called by hand."""

from __future__ import annotations

from pathlib import Path

from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.hub.fanout import FanOut
from servotune.hub.state import AXIS_SILENT_S, HubState
from servotune.link.base import Sample
from servotune.storage import Storage


class Axis:
    id = "ax"
    name = "ax"
    address = 0
    descriptor = slap2_descriptor(512)


class Line:
    id = "line"
    device = "slap2"
    path = "/dev/fake"
    baud = 19200
    state = "connected"

    def __init__(self) -> None:
        self.axes = [Axis()]
        self.counters = {"host_stalls": 0}


def judged(tmp_path: Path, *, host_stalls_from: float | None) -> list[tuple[float, str, str]]:
    """The axis' health, once a second for 12 s after its last sample at 1000; its link
    publishes its status every second, its ``host_stalls`` growing from
    ``host_stalls_from`` on (None: never)."""
    now = [1000.0]
    state = HubState(Storage(tmp_path / "db.sqlite"), FanOut(), clock=lambda: now[-1])
    line = Line()
    state.add_link(line)  # type: ignore[arg-type]
    state.link_entry("line").running = True
    state.on_link_status("line", "connected", "", 10.0, 20.0, 0)
    state.on_axis_health("ax", "ok", "")
    state.on_sample("ax", Sample(1000.0, {"position": 0.0}, {}))
    seen = []
    for second in range(1, 13):
        now.append(1000.0 + second)
        if host_stalls_from is not None and now[-1] >= host_stalls_from:
            line.counters["host_stalls"] += 1
        state.on_link_status("line", "connected", "", 0.0, 20.0, 0)
        state.status_tick(now[-1])
        entry = state.entry("ax")
        seen.append((float(second), entry.health, entry.health_message))
    return seen


def offline_after(seen: list[tuple[float, str, str]]) -> tuple[float, str] | None:
    return next(((t, message) for t, health, message in seen if health == "offline"), None)


def test_a_silent_axis_is_shown_offline(tmp_path: Path) -> None:
    offline = offline_after(judged(tmp_path, host_stalls_from=None))
    assert offline is not None and offline[0] == AXIS_SILENT_S
    assert "the device does not answer its polls" in offline[1]


def test_an_axis_whose_bytes_the_host_holds_is_offline_but_the_device_not_blamed(
    tmp_path: Path,
) -> None:
    # The link excuses its timeouts from 1 s on, the host holding its bytes throughout:
    # no live values, so not "ok" (the soak's truthfulness rule), but said why.
    offline = offline_after(judged(tmp_path, host_stalls_from=1001.0))
    assert offline is not None and offline[0] == AXIS_SILENT_S
    assert "holding the bytes back" in offline[1]
    assert "the device does not answer" not in offline[1]


def test_a_stall_of_the_whole_server_is_not_a_stalled_link(tmp_path: Path) -> None:
    """The server's loop did not run for 5 s (seen under a CPU hog: all three demo links
    shown "no status from the link for 5 s: its task is stalled" at once). Its links did
    not publish because nothing ran: said once, as the server's stall, and the links
    are judged from the loop's return - a link that stays silent after it is stalled."""
    now = [1000.0]
    state = HubState(Storage(tmp_path / "db.sqlite"), FanOut(), clock=lambda: now[-1])
    state.add_link(Line())  # type: ignore[arg-type]
    state.link_entry("line").running = True
    state.on_link_status("line", "connected", "", 10.0, 20.0, 0)
    state.on_axis_health("ax", "ok", "")
    state.on_sample("ax", Sample(1000.0, {"position": 0.0}, {}))
    state.take_telemetry(False)
    now.append(1005.0)  # nothing ran for 5 s; a queued status query is served first
    assert state.link_status("line").state == "connected"
    state.take_telemetry(False)  # the fan-out's heartbeat: the stall is seen
    state.status_tick(now[-1])
    assert state.link_status("line").state == "connected"
    assert state.entry("ax").health == "ok"  # its axis' silence was the server's too
    assert [e.message for e in state.events if "did not run for 5.0 s" in e.message]
    # The loop runs again (beats every 0.5 s), the link's status never comes.
    for t in range(1, 9):
        now.append(1005.0 + t / 2)
        state.take_telemetry(False)
        state.status_tick(now[-1])
    status = state.link_status("line")
    assert status.state == "error" and "its task is stalled" in status.message
