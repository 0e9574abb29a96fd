"""The link engine's silence rule and the host's excuse (servotune.link.engine): a
request that timed out while the host's tty layer held bytes back for longer than the
request listened is no evidence against the device; a line that is really silent
still shows ``error`` at once on a host that runs, and within TTY_STALL_EXCUSE_S on
one that stalls all the time. Clock and tty layer injected: nothing here depends on
the host's speed."""

from __future__ import annotations

from servotune.link.engine import SILENT_S, TTY_STALL_EXCUSE_S, LinkEngine
from servotune.transports.serial import SerialConnector
from tests.support.sink import RecordingSink


class Session:
    """Only what the rule asks of a device's link."""

    async def run_session(self, channel: object) -> None:
        raise AssertionError("not run")

    def link_down(self) -> None:
        pass

    def wire_limit_hz(self) -> float:
        return 10.0

    def achieved_rate_hz(self) -> float:
        return 10.0


class Channel:
    """A channel whose timeouts were all noticed on time (the server ran)."""

    def take_timeout_late_s(self) -> float:
        return 0.0


class TtyLayer:
    """The host tty layer's gauge: holding bytes back for ``held_s`` (0: it flows)."""

    def __init__(self) -> None:
        self.held = 0.0

    def held_s(self, window_s: float) -> float:
        return self.held


def connected_engine() -> tuple[LinkEngine, RecordingSink, list[float], TtyLayer]:
    sink = RecordingSink()
    now = [100.0]
    tty = TtyLayer()
    engine = LinkEngine(
        "line",
        "/dev/null",
        115200,
        SerialConnector("/dev/null", 115200),
        sink,
        Session(),
        clock=lambda: now[-1],
        tty_gauge=tty,
    )
    engine._channel = Channel()  # type: ignore[assignment]
    engine._opened_at = 100.0
    engine.set_state("connected", "open")
    return engine, sink, now, tty


def unanswered_at(engine: LinkEngine, now: list[float], times: list[float]) -> None:
    for t in times:
        now.append(t)
        engine.unanswered_request(0.1)  # a request listened 100 ms


def test_a_silent_device_on_a_host_that_runs_is_an_error_at_once() -> None:
    engine, sink, now, _ = connected_engine()
    unanswered_at(engine, now, [100.4, 100.7, 100.0 + SILENT_S])
    assert sink.states[-1][0] == "error" and "no answer from the device" in sink.states[-1][1]


def test_replies_held_in_the_hosts_tty_layer_are_no_silence() -> None:
    """The kernel's tty worker starved (measured under a CPU hog: a pty byte held 2.1 s
    while the server's own timers ran on time): the device answered, its bytes were
    held. Those timeouts are counted as host stalls, never shown as ``error``."""
    engine, sink, now, tty = connected_engine()
    tty.held = 0.4
    unanswered_at(engine, now, [100.4, 100.7, 101.0, 101.3, 101.6])
    assert [s for s, _ in sink.states] == ["connected"], sink.states
    assert engine.counters["host_stalls"] == 5
    engine.answered()  # the held bytes came through
    tty.held = 0.0
    unanswered_at(engine, now, [102.0, 102.3, 103.1])  # then the cable is cut
    assert sink.states[-1][0] == "error"


def test_a_cut_line_on_a_host_stalled_all_the_time_still_shows() -> None:
    engine, sink, now, tty = connected_engine()
    tty.held = 0.4
    stalled = [100.4 + 0.5 * i for i in range(int(TTY_STALL_EXCUSE_S / 0.5))]
    unanswered_at(engine, now, stalled)  # a stall of 3.0 s was measured: excused
    assert [s for s, _ in sink.states] == ["connected"]
    unanswered_at(engine, now, [100.4 + TTY_STALL_EXCUSE_S + t for t in (0.0, 0.2, 0.4)])
    assert sink.states[-1][0] == "error", sink.states
