"""The host tty layer's canary (servotune.transports.tty_probe): a real pseudo-terminal,
the probe's clock injected, so that how long a byte was "held" is the clock's doing,
never the host's speed."""

from __future__ import annotations

import asyncio

from servotune.transports.tty_probe import TtyProbe


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


async def test_held_is_the_longest_flight_in_the_window_and_the_one_in_flight() -> None:
    clock = Clock()
    probe = TtyProbe(period_s=3600.0, clock=clock)  # one canary byte only
    assert probe.start()
    try:
        await asyncio.sleep(0)  # the canary is written at clock 0
        assert probe.held_s(0.1) == 0.0 and probe.canaries == 0
        clock.now = 0.3  # the host's tty layer holds it (as far as the clock says)
        assert probe.held_s(0.1) == 0.3  # in flight: held until now
        for _ in range(30_000):  # it comes through whenever the kernel delivers it
            if probe.canaries:
                break
            await asyncio.sleep(0.001)
        assert probe.canaries == 1
        assert probe.held_s(0.1) == 0.3  # came through within the window
        clock.now = 0.5
        assert probe.held_s(0.1) == 0.0  # came through before the window: no evidence
        assert probe.held_s(0.3) == 0.3
    finally:
        await probe.close()
    assert probe.held_s(10.0) == 0.3  # closed: what it saw stays, nothing in flight
