"""The dead-man under load: it keeps its promise for a vanished client and
does not fire on a live, busy one (docs/control.md, "The dead-man").

A tab's heartbeats come from a worker on a socket of their own (``/ws?beat=<id>``),
with ``page_age_ms``: how long ago the page itself last ran. The delays are injected
deterministically: the page's stall is the ``page_age_ms`` the test's "worker" reports,
never a sleep the test hopes the machine keeps.

Time is the server's own: the control lock runs on a ``StepClock`` that only the test
moves, a heartbeat period (or a watchdog period) at a time, each step followed by a
whole pass of the dead-man's watchdog. So the rules are asserted exactly on the
server's time - no trip while a client is heard within the lease, a trip in the first
watchdog pass after it, a frozen page after ``frozen_page_s`` - whatever the load on
the machine. How long the whole chain takes in real time (the lapse, the STOP on the
wire: the 500 ms promise) is a figure of the machine, measured by
``scripts/perf_deadman.py`` (docs/control.md).
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
import websockets
from websockets.typing import Origin

from servotune.hub.control_client import ControlClient, ControlSettings
from servotune.hub.control_lock import ControlLock
from tests.support.control import (
    RawWebsocket,
    Server,
    can_cut_the_network,
    control_server,
    cut_network,
    take_with_raw_client,
)

VM, PM = 1 << 2, 1 << 3
SETTINGS = ControlSettings(request_timeout_s=0.5, autopilot_resume_s=60.0)
BEAT_S = SETTINGS.heartbeat_period_s
# Real time allowed for something the loop must get to (a heartbeat read, a watchdog
# pass, a STOP on the wire): a bound on liveness only, never the figure under test.
LIVENESS_S = 15.0


class StepClock:
    """The control lock's clock (``AppConfig.control_clock``): it stands still until the
    test steps it. ``pace()`` keeps it from running ahead of real time from that moment
    on, where the server weighs it against real evidence (the kernel's last TCP
    acknowledgement of a connection, in real seconds)."""

    def __init__(self) -> None:
        self.t = 1000.0
        self._paced: tuple[float, float] | None = None

    def __call__(self) -> float:
        return self.t

    def pace(self) -> None:
        self._paced = (self.t, time.monotonic())

    async def step(self, server: Server, dt_s: float) -> None:
        """Move the clock by ``dt_s`` and wait until one whole watchdog pass ran on the
        new time."""
        self.t += dt_s
        if self._paced is not None:
            ahead = (self.t - self._paced[0]) - (time.monotonic() - self._paced[1])
            if ahead > 0:
                await asyncio.sleep(ahead)
        passes = manager(server).watchdog_passes
        await until(server, lambda m: m.watchdog_passes >= passes + 2, "two watchdog passes")


@pytest.fixture
async def clock() -> StepClock:
    return StepClock()


@pytest.fixture
async def server(tmp_path: Path, clock: StepClock) -> AsyncIterator[Server]:
    async with control_server(tmp_path, SETTINGS, addresses=[0], clock=clock) as live:
        yield live


def manager(server: Server) -> ControlLock:
    control: ControlLock = server.app.state.control
    return control


def client_of(server: Server, client_id: str) -> ControlClient:
    client = manager(server).client(client_id)
    assert client is not None, "the tab is not connected"
    return client


async def until(server: Server, done: Callable[[ControlLock], Any], what: str = "") -> None:
    deadline = time.monotonic() + LIVENESS_S
    while not done(manager(server)):
        assert time.monotonic() < deadline, f"not within {LIVENESS_S} s: {what or done}"
        await asyncio.sleep(0.002)


async def stop_on_the_wire(server: Server, after: float) -> float:
    """When the dead-man's controlled stop (pm, from velocity mode) reached the device."""
    deadline = time.monotonic() + LIVENESS_S
    while (at := server.wire.first("pm", 0, after)) is None:
        assert time.monotonic() < deadline, "the dead-man never stopped the axis"
        await asyncio.sleep(0.005)
    return at


async def send_beat(
    server: Server, socket: RawWebsocket, client_id: str, *page_age_ms: int | None
) -> None:
    """One heartbeat - a worker's with the page age if one is given (None: no jog held),
    else the page's own - and wait until the server has read it."""
    client = client_of(server, client_id)
    heard = client.heartbeats
    payload: dict[str, Any] = {"type": "heartbeat"}
    if page_age_ms:
        payload["page_age_ms"] = page_age_ms[0]
    socket.send_text(json.dumps(payload))
    await until(server, lambda _: client.heartbeats > heard, "the server reading a heartbeat")


async def busy_tab(server: Server) -> tuple[RawWebsocket, RawWebsocket, str]:
    """A tab that took line-0 and set it in velocity mode; its page sends nothing from now
    on (busy drawing): its worker's socket is returned to beat with."""
    main, client_id, beat_task = await take_with_raw_client(server, "line-0")
    beat_task.cancel()  # the page's own heartbeats stop: only the worker beats now
    response = await server.client.post(
        "/api/axes/line-0/commands",
        json={"command": "velocity_mode"},
        headers={"X-Servotune-Client": client_id},
    )
    assert response.status_code == 200, response.text
    worker = await RawWebsocket.connect(server.port, f"/ws?beat={client_id}")
    await send_beat(server, worker, client_id, 0)
    return main, worker, client_id


async def beat(
    server: Server,
    clock: StepClock,
    worker: RawWebsocket,
    client_id: str,
    page_age_ms: Callable[[float], int | None],
    seconds: float,
) -> None:
    """Worker heartbeats every BEAT_S of the server's time for ``seconds``, each
    reporting the page age the test injects for that moment."""
    for i in range(round(seconds / BEAT_S)):
        await send_beat(server, worker, client_id, page_age_ms(i * BEAT_S))
        await clock.step(server, BEAT_S)


async def test_a_busy_page_keeps_its_axes_while_its_worker_beats(
    server: Server, clock: StepClock
) -> None:
    main, worker, client_id = await busy_tab(server)
    lapses = manager(server).lapses
    mark = time.monotonic()

    # The page stalls for up to 1.9 s (long tasks of a loaded browser), twice; its
    # own heartbeats would have been 1.9 s late. The worker's come on time.
    def stalled(t: float) -> int:
        return round(1000 * min(1.9, t % 2.0))

    await beat(server, clock, worker, client_id, stalled, 4.2)
    # No jog held: the worker reports no page age, however long the page is stalled
    # (seen in the soak: 16.6 s at a load of 50); nothing it started needs a release.
    await beat(server, clock, worker, client_id, lambda t: None, 3.0)
    assert manager(server).lapses == lapses, "a live, busy tab lost its axis"
    assert "pm" not in [line for _, line in server.wire.since(mark, 0)]
    assert server.bus.module(0).rss & VM
    await main.close_quietly()
    await worker.close_quietly()


async def test_a_page_frozen_with_a_jog_held_loses_its_axes(
    server: Server, clock: StepClock
) -> None:
    main, worker, client_id = await busy_tab(server)
    lapses = manager(server).lapses
    frozen_at, mark = clock.t, time.monotonic()
    # From now on the page does not run at all while a jog is held: the worker says so
    # (it reports the page's age only while a hold-to-run control is engaged).
    while manager(server).lapses == lapses:
        assert clock.t - frozen_at < 3 * SETTINGS.frozen_page_s, "a frozen page kept its axis"
        await send_beat(server, worker, client_id, round(1000 * (clock.t - frozen_at)))
        await clock.step(server, BEAT_S)
    frozen_for = clock.t - frozen_at
    # Lapsed in the watchdog pass after the page's age passed frozen_page_s: within
    # one heartbeat period of it on the server's clock, never before.
    assert SETTINGS.frozen_page_s - 1e-6 <= frozen_for <= SETTINGS.frozen_page_s + BEAT_S + 1e-6
    await stop_on_the_wire(server, mark)
    reply = await main.wait_for(lambda m: m["type"] == "control_reply" and m["action"] == "lapse")
    assert "frozen" in reply["message"]
    assert not server.bus.module(0).rss & VM and server.bus.module(0).rss & PM
    await main.close_quietly()
    await worker.close_quietly()


async def test_a_tab_that_vanishes_with_a_reset_stops_at_once(
    server: Server, clock: StepClock
) -> None:
    """RST (the tab's process killed, the browser closed): the connection closes and the
    axes lapse at once - not after the lease: the server's clock does not move."""
    for _trial in range(3):
        main, worker, client_id = await busy_tab(server)
        await beat(server, clock, worker, client_id, lambda t: 0, 0.3)
        lapses, gone_t, mark = manager(server).lapses, clock.t, time.monotonic()
        main.drop()
        worker.drop()
        await stop_on_the_wire(server, mark)
        assert manager(server).lapses == lapses + 1
        assert clock.t == gone_t
        await main.close_quietly()
        await worker.close_quietly()


async def test_a_tab_cut_off_the_network_stops_after_its_lease(
    server: Server, clock: StepClock
) -> None:
    """A network cut (a laptop asleep, a cable pulled): the worker's heartbeats and every
    acknowledgement of the tab's machine are lost. No lapse while the server's time
    since the last heartbeat is within the lease; the lapse in the first watchdog pass
    after it."""
    if why := can_cut_the_network():
        pytest.skip(why)
    period = SETTINGS.watchdog_period_s
    for _trial in range(3):
        main, worker, client_id = await busy_tab(server)
        await beat(server, clock, worker, client_id, lambda t: 0, 0.3)
        await send_beat(server, worker, client_id, 0)
        heard_t, lapses, mark = (
            client_of(server, client_id).heard_s,
            manager(server).lapses,
            time.monotonic(),
        )
        with cut_network(worker.port, main.port):
            clock.pace()
            while manager(server).lapses == lapses:
                assert (
                    clock.t - heard_t <= SETTINGS.lease_s + 1e-6 or manager(server).lapses > lapses
                ), "no lapse in the pass after the lease ran out"
                await clock.step(server, period)
            silent_s = clock.t - heard_t
            assert SETTINGS.lease_s < silent_s <= SETTINGS.lease_s + period + 1e-6, silent_s
            await stop_on_the_wire(server, mark)
        await main.close_quietly()
        await worker.close_quietly()


async def test_a_live_connection_forgives_late_heartbeats_within_the_grace(
    server: Server, clock: StepClock
) -> None:
    """A browser starved of CPU: its heartbeats (the page's own, no worker) come up to
    1.5 s late on the server's clock; its machine acknowledges the telemetry and the
    server's probes meanwhile (loopback: the kernel, in real time, so the clock is
    paced). No trip; with the network cut, the same silence trips in the first
    watchdog pass after the lease."""
    main, client_id, beat_task = await take_with_raw_client(server, "line-0")
    beat_task.cancel()
    lapses = manager(server).lapses
    period = SETTINGS.watchdog_period_s
    clock.pace()
    for gap in (0.1, 0.6, 1.2, 0.1, 1.5, 0.1, 0.9):
        await send_beat(server, main, client_id)
        for _ in range(round(gap / period)):
            await clock.step(server, period)
    await send_beat(server, main, client_id)
    assert manager(server).lapses == lapses, "a live, late client lost its axis"
    assert manager(server).holder("line-0") is not None
    if not can_cut_the_network():
        heard_t = client_of(server, client_id).heard_s
        with cut_network(main.port):
            clock.pace()
            while manager(server).holder("line-0") is not None:
                assert clock.t - heard_t <= SETTINGS.lease_s + period + 1e-6, (
                    "the cut client kept its axis past the lease"
                )
                await clock.step(server, period)
            assert clock.t - heard_t > SETTINGS.lease_s
    await main.close_quietly()


async def test_a_live_connection_is_forgiven_for_the_grace_only(
    server: Server, clock: StepClock
) -> None:
    """A tab whose machine acknowledges everything but whose browser sends no heartbeat
    at all (the whole renderer stuck): forgiven for ``alive_grace_s`` at most on the
    server's clock, then the dead-man stops it, and says that its machine is alive
    (not "cannot be checked", as the 60 s soak's false stop read)."""
    main, client_id, beat_task = await take_with_raw_client(server, "line-0")
    beat_task.cancel()
    await send_beat(server, main, client_id)
    heard_t, lapses = client_of(server, client_id).heard_s, manager(server).lapses
    period = SETTINGS.watchdog_period_s
    clock.pace()
    while manager(server).lapses == lapses:
        assert clock.t - heard_t <= SETTINGS.alive_grace_s + period + 1e-6, "kept past the grace"
        await clock.step(server, period)
    reply = await main.wait_for(lambda m: m["type"] == "control_reply" and m["action"] == "lapse")
    assert "acknowledged" in reply["message"], reply["message"]
    if clock.t - heard_t > SETTINGS.alive_grace_s:
        assert "forgiven 2 s only" in reply["message"], reply["message"]
    await main.close_quietly()


async def test_heartbeats_of_the_page_itself_late_within_the_lease_do_not_trip(
    server: Server, clock: StepClock
) -> None:
    """Without a worker (a browser without workers): the page's own heartbeats, each
    gap injected on the server's clock, up to 100 ms short of the lease."""
    main, client_id, beat_task = await take_with_raw_client(server, "line-0")
    beat_task.cancel()
    lapses = manager(server).lapses
    gaps = [0.1, 0.2, 0.25, 0.1, 0.15, 0.25, 0.25, 0.1] * 2
    for gap in gaps:
        await send_beat(server, main, client_id)
        await clock.step(server, gap)
    await send_beat(server, main, client_id)
    assert manager(server).lapses == lapses
    assert manager(server).holder("line-0") is not None
    await main.close_quietly()


async def test_a_beat_socket_for_no_open_tab_is_refused(server: Server) -> None:
    with pytest.raises(websockets.InvalidStatus) as refused:
        async with websockets.connect(
            f"{server.ws_url}?beat=no-such-client", origin=Origin(server.base_url)
        ):
            pass
    assert refused.value.response.status_code == 403
