"""Links that never die and never lie: fault injection on the real drivers.

Each fault is injected in the simulated device, between the device and the pty (a
``Tap`` that records every byte the device received and can hold back, drop or
replace what it sends), or as an exception inside a driver's poll. After every fault
the link must recover, its state must be right at every step (the sequence recorded
by the sink), and a STOP sent afterwards must reach the wire (asserted on the
simulator side's own record of what it received).
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import re
import threading
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest

from servotune.devices.slap2.link import Slap2Axis, Slap2Link, Slap2LinkConfig
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.devices.z1100 import codec as zcodec
from servotune.devices.z1100.link import Z1100Axis, Z1100Link, Z1100LinkConfig
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.demo import Z1100_LOADS_KG_M2, write_demo_flash
from servotune.link.base import DriverError, InvalidArgumentError, LinkDownError
from servotune.sim.pty import PtySimulator
from servotune.transports.serial import SerialConnector
from tests.support.servers import local_client, use_csrf_token
from tests.support.sink import RecordingSink
from tests.support.supervision import Tap, hub_on_line
from tests.support.waiting import wait_for

Z_BAUD = 38400
CTRL_X = 0x18


def states_after(sink: RecordingSink, index: int) -> list[str]:
    return [state for state, _ in sink.states[index:]]


# --- fixtures -----------------------------------------------------------------------


class ZLine:
    def __init__(self, link: Z1100Link, sink: RecordingSink, tap: Tap) -> None:
        self.link, self.sink, self.tap = link, sink, tap

    def axis(self, index: int) -> Z1100Axis:
        axis = self.link.axes[index]
        assert isinstance(axis, Z1100Axis)
        return axis

    def requests_since(self, mark: int) -> list[zcodec.Request]:
        events = zcodec.RequestDecoder().feed(self.tap.since(mark))
        return [e for e in events if isinstance(e, zcodec.Request)]

    def samples(self, index: int) -> int:
        return len(self.sink.samples[self.link.axis_id(index)])


@contextlib.asynccontextmanager
async def z_line(tmp_path: Path, *, verify_period_s: float = 2.0) -> AsyncIterator[ZLine]:
    flash = tmp_path / "flash.json"
    write_demo_flash(flash)
    chip = Z1100Chip.with_loads(Z1100_LOADS_KG_M2, flash_path=flash, jumper_baud=Z_BAUD)
    tap = Tap(chip)
    with PtySimulator(tap, baud=Z_BAUD) as sim:
        sink = RecordingSink()
        link_config = Z1100LinkConfig(
            link_id="chip", path=sim.path, baud=Z_BAUD, verify_period_s=verify_period_s
        )
        link = Z1100Link(link_config, SerialConnector(sim.path, Z_BAUD), sink)
        task = asyncio.create_task(link.run())
        try:
            await wait_for(lambda: link.state == "connected", 10, "the chip link")
            line = ZLine(link, sink, tap)
            await wait_for(lambda: all(line.samples(i) > 2 for i in range(3)), 10, "samples")
            yield line
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


class SLine:
    def __init__(self, link: Slap2Link, sink: RecordingSink, tap: Tap, bus: Slap2Line) -> None:
        self.link, self.sink, self.tap, self.bus = link, sink, tap, bus

    def axis(self, address: int) -> Slap2Axis:
        axis = next(a for a in self.link.axes if a.address == address)
        assert isinstance(axis, Slap2Axis)
        return axis

    def samples(self, address: int) -> int:
        return len(self.sink.samples[self.link.axis_id(address)])

    def resets(self) -> list[tuple[str, str]]:
        return [(a, m) for a, h, m in self.sink.health_log if h == "reset"]


@contextlib.asynccontextmanager
async def s_line(tmp_path: Path, addresses: tuple[int, ...] = (0, 1)) -> AsyncIterator[SLine]:
    bus = Slap2Line([Slap2Module(a, eeprom_path=tmp_path / f"eeprom_{a}.json") for a in addresses])
    tap = Tap(bus)
    with PtySimulator(tap, baud=19200) as sim:
        sink = RecordingSink()
        config = Slap2LinkConfig(
            link_id="line", path=sim.path, addresses=list(addresses), baud=19200
        )
        link = Slap2Link(config, SerialConnector(sim.path, 19200), sink)
        task = asyncio.create_task(link.run())
        try:
            await wait_for(lambda: link.state == "connected", 10, "the SLAP2 link")
            line = SLine(link, sink, tap, bus)
            await wait_for(lambda: all(line.samples(a) > 2 for a in addresses), 10, "samples")
            yield line
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


# --- an exception inside a poll --------------------------------------------------------


async def test_exception_in_a_z1100_poll_restarts_the_session_and_stop_reaches_the_wire(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    async with z_line(tmp_path) as line:
        original = line.link._poll_cycle
        injected = asyncio.Event()

        async def failing_poll() -> None:
            if not injected.is_set():
                injected.set()
                raise RuntimeError("injected fault in the poll")
            await original()

        monkeypatch.setattr(line.link, "_poll_cycle", failing_poll)
        index = len(line.sink.states)
        await asyncio.wait_for(injected.wait(), 10)
        await wait_for(
            lambda: "connected" in states_after(line.sink, index + 1), 15, "the link back"
        )
        seen = line.sink.states[index:]
        assert seen[0][0] == "error"
        assert "RuntimeError: injected fault in the poll" in seen[0][1]
        assert "reconnecting" in seen[0][1]
        # error -> connecting (probe) -> connected, never connected in between
        assert [s for s, _ in seen][:3] == ["error", "connecting", "connected"]
        assert line.link.counters["restarts"] == 1
        assert any("internal error" in m for _, _, m in line.sink.events)
        count = line.samples(1)
        await wait_for(lambda: line.samples(1) > count + 3, 10, "polling again")
        mark = line.tap.mark()
        await line.axis(1).stop()
        estops = [r for r in line.requests_since(mark) if r.command is zcodec.Command.SET_ESTOP]
        assert estops and estops[0].data == zcodec.pack_axes([1])


async def test_exception_in_a_slap2_poll_restarts_the_session_and_stop_reaches_the_wire(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    async with s_line(tmp_path) as line:
        original = line.link._poll_step
        injected = asyncio.Event()

        async def failing_poll(online: list[object]) -> None:
            if not injected.is_set():
                injected.set()
                raise KeyError("injected")
            await original(online)  # type: ignore[arg-type]

        monkeypatch.setattr(line.link, "_poll_step", failing_poll)
        index = len(line.sink.states)
        await asyncio.wait_for(injected.wait(), 10)
        await wait_for(
            lambda: "connected" in states_after(line.sink, index + 1), 15, "the link back"
        )
        assert [s for s, _ in line.sink.states[index:]][:3] == ["error", "connecting", "connected"]
        assert "KeyError" in line.sink.states[index][1]
        count = line.samples(0)
        await wait_for(lambda: line.samples(0) > count + 3, 10, "polling again")
        mark = line.tap.mark()
        await line.axis(0).stop()
        assert b"st\r" in line.tap.since(mark)
        assert not line.resets()


# --- a Z1100 Get answered with the moving bits, a late reply ---------------------------


async def test_z1100_get_answered_with_moving_bits_is_a_desync_not_a_refusal(
    tmp_path: Path,
) -> None:
    async with z_line(tmp_path) as line:
        armed = threading.Event()
        armed.set()

        def moving_reply(byte: int, out: bytes) -> bytes:
            if armed.is_set() and len(out) == zcodec.REPLY_SIZE:
                armed.clear()  # the next reply (to a poll: a Get) says "motor 2 moves"
                return zcodec.Reply(zcodec.ReplyCode.MOVING_2).encode()
            return out

        index = len(line.sink.states)
        desyncs = line.link.counters["desyncs"]
        line.tap.rewrite = moving_reply
        await wait_for(lambda: not armed.is_set(), 5, "the fault")
        count = line.samples(2)
        await wait_for(lambda: line.samples(2) > count + 5, 10, "polling to go on")
        assert line.link.counters["desyncs"] > desyncs
        assert states_after(line.sink, index) == []  # stayed connected throughout
        assert line.link.state == "connected"
        assert not any("refused" in m for _, _, m in line.sink.events)
        mark = line.tap.mark()
        await line.axis(0).stop()
        assert any(r.command is zcodec.Command.SET_ESTOP for r in line.requests_since(mark))


async def test_z1100_late_reply_is_dropped_and_not_taken_for_the_next_one(tmp_path: Path) -> None:
    async with z_line(tmp_path) as line:
        await line.axis(0).write_params({"vmax": 54321})
        armed = threading.Event()
        armed.set()
        tap = line.tap

        def late_reply(byte: int, out: bytes) -> bytes:
            if armed.is_set() and len(out) == zcodec.REPLY_SIZE:
                armed.clear()
                # After the 100 ms reply timeout; the chip answers in order, so what it
                # answers next comes after this.
                tap.send_late(out, 0.13, in_order=True)
                return b""
            return out

        index = len(line.sink.states)
        retries = line.link.counters["retries"]
        tap.rewrite = late_reply
        await wait_for(lambda: not armed.is_set(), 5, "the fault")
        count = line.samples(0)
        await wait_for(lambda: line.samples(0) > count + 5, 10, "polling to go on")
        assert line.link.counters["retries"] > retries
        assert states_after(line.sink, index) == []
        # Every value read afterwards is the right one (no reply taken for another).
        assert (await line.axis(0).read_params())["vmax"] == 54321
        mark = line.tap.mark()
        await line.axis(0).stop()
        assert any(r.command is zcodec.Command.SET_ESTOP for r in line.requests_since(mark))


async def test_z1100_starved_chip_answering_late_is_no_chip_reset(tmp_path: Path) -> None:
    """A host so starved that replies trickle in behind their requests (each reply
    held back 0..300 ms, in order, for 10 s: many land after their 100 ms timeout,
    while the retry is already out). No reply may be taken for another's: a late
    GetError 0 read as GetVmax would be a "chip reset" witness (seen in the demo
    under a CPU hog). Before the fence: 2 of 6 runs raised a false reset."""
    async with z_line(tmp_path, verify_period_s=0.05) as line:
        await line.axis(0).write_params({"vmax": 54321})
        # Every motor holds a target job: then the verify step also reads GetJob, whose
        # reset cue (0, free shaft) a late GetError 0 at rest imitates exactly.
        for axis in range(3):
            motor = line.link.motor(axis)
            assert motor.position is not None
            await line.axis(axis).command("go_to_target", {"target": motor.position + 300})
        await wait_for(
            lambda: all(m.job == zcodec.Job.TARGET for m in map(line.link.motor, range(3))),
            5,
            "the target jobs",
        )
        await asyncio.sleep(0.5)
        await wait_for(
            lambda: not any(line.link.motor(axis).running for axis in range(3)), 10, "the moves"
        )
        tap = line.tap
        rng = random.Random(8)
        starving = threading.Event()
        starving.set()

        def late(byte: int, out: bytes) -> bytes:
            if starving.is_set() and len(out) == zcodec.REPLY_SIZE:
                tap.send_late(out, rng.random() * 0.3, in_order=True)
                return b""
            return out

        retries = line.link.counters["retries"]
        events = len(line.sink.events)
        health = len(line.sink.health_log)
        at_rest = {axis: line.sink.samples[line.link.axis_id(axis)][-1] for axis in range(3)}
        first = {axis: line.samples(axis) for axis in range(3)}
        tap.rewrite = late
        await asyncio.sleep(10)
        starving.clear()
        await asyncio.sleep(1.5)  # what was held back arrives; polling goes on
        assert line.link.counters["retries"] > retries  # the fault did bite
        # The motors rest: every sample read meanwhile shows the rest position (a reply
        # taken for another's would show a following error, a speed or a gain).
        for axis in range(3):
            rest = at_rest[axis].channels["position"]
            seen = line.sink.samples[line.link.axis_id(axis)][first[axis] :]
            wrong = [
                (s.channels["position"], s.channels["following_error"])
                for s in seen
                if s.channels["position"] != rest or abs(s.channels["following_error"] or 0) > 2
            ]
            assert wrong == [], (axis, rest, len(seen))
        resets = [entry for entry in line.sink.health_log[health:] if entry[1] == "reset"]
        assert resets == []
        alarms = [
            text for _, _, text in line.sink.events[events:] if "reset" in text or "stall" in text
        ]
        assert alarms == []
        assert (await line.axis(0).read_params())["vmax"] == 54321
        mark = line.tap.mark()
        await line.axis(0).stop()
        assert any(r.command is zcodec.Command.SET_ESTOP for r in line.requests_since(mark))


# --- SLAP2: late Ctrl-X echo, a missed echo, a banner -----------------------------------


async def test_slap2_late_ctrl_x_echo_is_not_taken_for_the_next_echo(tmp_path: Path) -> None:
    async with s_line(tmp_path) as line:
        armed = threading.Event()
        armed.set()
        tap = line.tap

        def late_ctrl_x(byte: int, out: bytes) -> bytes:
            if byte == CTRL_X and armed.is_set() and out:
                armed.clear()
                tap.send_late(out, 0.2)  # later than the driver's character timeout
                return b""
            return out

        tap.rewrite = late_ctrl_x
        index = len(line.sink.states)
        errors = line.link.errors
        # One lost echo makes the driver abandon that command with Ctrl-X.
        await _drop_one_echo(line)
        await wait_for(lambda: not armed.is_set(), 5, "the Ctrl-X")
        await asyncio.sleep(0.4)
        # Commands and polls go on: the late 0x18 was skipped, not an echo mismatch.
        for kd in (11, 12, 13):
            assert await line.axis(1).write_params({"kd": kd}) == {"kd": kd}
        assert line.bus.module(1).settings["kd"] == 13
        assert line.link.errors > errors
        assert states_after(line.sink, index) == []
        assert not line.resets()
        mark = line.tap.mark()
        await line.axis(1).stop()
        assert b"st\r" in line.tap.since(mark)


async def _drop_one_echo(line: SLine) -> None:
    """Drop the echo of the next byte the host sends (whatever the command)."""
    armed = threading.Event()
    armed.set()
    chained = line.tap.rewrite

    def drop(byte: int, out: bytes) -> bytes:
        if armed.is_set() and out and byte != CTRL_X:
            armed.clear()
            out = out[1:]
        return chained(byte, out) if chained is not None else out

    line.tap.rewrite = drop
    await wait_for(lambda: not armed.is_set(), 5, "the dropped echo")


async def test_slap2_missed_select_echo_does_not_flag_reset(tmp_path: Path) -> None:
    """One lost echo of ``se`` (a slow host) makes the driver select blind; the module
    answers, nothing else says reset: counted as a desync, no reset flag."""
    async with s_line(tmp_path) as line:
        await line.axis(1).write_params({"kp": 150})
        armed = threading.Event()
        armed.set()
        previous = bytearray(b"\r")

        def drop_se_echo(byte: int, out: bytes) -> bytes:
            start = previous[-1:] == b"\r"
            previous[:] = bytes([byte])
            if armed.is_set() and start and byte == ord("s") and out:
                armed.clear()  # the first echo of the next "se": lost
                return out[1:]
            return out

        desyncs = line.link.counters["desyncs"]
        line.tap.rewrite = drop_se_echo
        await wait_for(lambda: not armed.is_set(), 5, "the lost se echo")
        for address in (0, 1):
            count = line.samples(address)
            await wait_for(lambda a=address, c=count: line.samples(a) > c + 5, 10, "polls")
        await wait_for(lambda: line.link.counters["desyncs"] > desyncs, 5, "the desync count")
        assert not line.resets(), line.resets()
        assert line.link.state == "connected"
        assert not any(h == "offline" for _, h, _ in line.sink.health_log[-4:])


async def test_slap2_own_echo_among_stray_bytes_is_no_banner(tmp_path: Path) -> None:
    async with s_line(tmp_path) as line:
        dropped = line.link.counters["dropped_bytes"]
        events = len(line.sink.events)
        line.tap.send_late(b"se0\rrss\r", 0.0)  # late echoes of the driver's own commands
        await wait_for(
            lambda: line.link.counters["dropped_bytes"] > dropped, 5, "the stray bytes dropped"
        )
        await asyncio.sleep(0.3)
        assert not line.resets()
        assert not any("banner" in m for _, _, m in line.sink.events[events:])


async def test_slap2_power_on_banner_flags_reset(tmp_path: Path) -> None:
    async with s_line(tmp_path) as line:
        await line.axis(0).write_params({"kp": 150})
        line.tap.power_cycle(0)
        await wait_for(lambda: bool(line.resets()), 5, "the reset flag")
        axis_id, message = line.resets()[0]
        assert axis_id == "line-0" and "banner" in message


async def test_slap2_console_refuses_control_characters_and_reports_refusals(
    tmp_path: Path,
) -> None:
    async with s_line(tmp_path) as line:
        mark = line.tap.mark()
        for bad in ("rp\rsv0", "sv0\n", "rp\x18", "\x0bcal", "kp\t1"):
            with pytest.raises(InvalidArgumentError) as refused:
                await line.axis(0).console(bad)
            assert refused.value.field == "line"
        sent = line.tap.since(mark)
        assert b"sv0" not in sent and b"rpsv" not in sent and bytes([CTRL_X]) not in sent
        # A command the module refuses answers with the refusal, not with [""].
        from servotune.link.base import DeviceRefusedError

        with pytest.raises(DeviceRefusedError, match="refused"):
            await line.axis(0).console("ma100")  # needs position mode


# --- the hub: a link whose task died or stalled is not connected -----------------------


class _FakeLink:
    device = "z1100"
    path = "/dev/fake"
    baud = 9600

    def __init__(self, hub_sink: Callable[[], object], behaviour: str) -> None:
        self.id = "fake"
        self.axes: list[object] = []
        self.state = "connecting"
        self.runs = 0
        self._sink = hub_sink
        self._behaviour = behaviour

    async def run(self) -> None:
        self.runs += 1
        hub = self._sink()
        hub.on_link_status(self.id, "connected", "fake", 10.0, 20.0, 0)  # type: ignore[attr-defined]
        if self._behaviour == "crash" and self.runs == 1:
            raise RuntimeError("driver bug")
        await asyncio.Event().wait()  # stalls without ever publishing again


async def test_hub_never_shows_a_dead_or_stalled_link_connected(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from servotune.hub.hub import Hub
    from servotune.storage import Storage

    monkeypatch.setattr("servotune.hub.state.STATUS_STALE_S", 0.5)
    holder: list[Hub] = []
    crash = _FakeLink(lambda: holder[0], "crash")
    hub = Hub([crash], Storage(tmp_path / "db.sqlite"))  # type: ignore[list-item]
    holder.append(hub)
    await hub.start()
    try:
        # The crash: shown as error with the reason, then restarted by the hub.
        await wait_for(lambda: crash.runs >= 2, 5, "the hub to restart the link")
        assert any("driver bug" in e.message and "restarting" in e.message for e in hub._events)
        assert hub.link_status("fake").counters.get("restarts") == 1
        # The restarted run published connected once and then stalled: not connected.
        await wait_for(lambda: hub.link_status("fake").state != "connected", 3, "stale status")
        status = hub.link_status("fake")
        assert status.state == "error" and "stalled" in status.message
        assert status.rate_hz == 0.0
    finally:
        await hub.stop()


async def test_hub_stop_during_outage_is_sent_after_reconnect(tmp_path: Path) -> None:
    """STOP while the line is unplugged: it says it was not sent and that it will be
    sent on reconnect, and it is (the simulator receives ``st``)."""

    bus = Slap2Line([Slap2Module(0, eeprom_path=tmp_path / "eeprom_0.json")])
    tap = Tap(bus)
    with PtySimulator(tap, baud=19200, link_path=str(tmp_path / "tty")) as sim:
        hub, link = hub_on_line(sim.path, [0], tmp_path)
        await hub.start()
        try:
            await wait_for(lambda: hub.link_status("line").state == "connected", 10, "link")
            sim.unplug()
            await wait_for(lambda: hub.link_status("line").state != "connected", 10, "down")
            assert await hub.stop_all() == ["line-0"]
            message = next(e.message for e in reversed(hub._events) if "STOP" in e.message)
            assert "not delivered" in message and "will be sent" in message
            with pytest.raises(LinkDownError):
                await link.axes[0].stop()
            mark = tap.mark()
            sim.replug()
            await wait_for(lambda: b"st\r" in tap.since(mark), 15, "the STOP on the wire")
            await wait_for(
                lambda: any("STOP sent" in e.message for e in hub._events), 5, "the event"
            )
            assert not hub.entry("line-0").stop_on_reconnect
        finally:
            await hub.stop()


async def test_api_console_refuses_control_characters_and_logs_lines(tmp_path: Path) -> None:
    """Through the API: 422 naming ``line`` and nothing sent; a refusal is a 409 with
    the module's reason; every line sent is an event."""

    from servotune.api.app import AppConfig, create_app
    from servotune.config import LinkSpec

    bus = Slap2Line([Slap2Module(0, eeprom_path=tmp_path / "eeprom_0.json")])
    tap = Tap(bus)
    with PtySimulator(tap, baud=19200) as sim:
        spec = LinkSpec("slap2", sim.path, "line", 19200, [0])
        app = create_app(AppConfig(links=[spec], data_dir=tmp_path / "data"))
        async with app.router.lifespan_context(app):
            hub = app.state.hub
            await wait_for(lambda: hub.link_status("line").state == "connected", 10, "link")
            async with local_client(app) as client:
                await use_csrf_token(client)
                url = "/api/axes/line-0/console"
                mark = tap.mark()
                for bad in ("rp\rsv0", "se0\x18", "kp 1\n"):
                    response = await client.post(url, json={"line": bad})
                    assert response.status_code == 422, response.text
                    assert response.json()["field"] == "line"
                sent = tap.since(mark)
                assert b"sv0" not in sent and bytes([CTRL_X]) not in sent
                response = await client.post(url, json={"line": "ma 100"})  # pm is off
                assert response.status_code == 409, response.text
                assert "refused" in response.json()["detail"]
                response = await client.post(url, json={"line": "qp"})
                assert response.status_code == 200 and response.json()["reply"] == ["40"]
                messages = [e.message for e in hub._events]
                assert any("console 'qp'" in m for m in messages)
                assert any("console 'ma 100'" in m and "refused" in m for m in messages)


async def test_slap2_listing_with_a_pause_mid_reply_is_read_whole(tmp_path: Path) -> None:
    """A listing ends when the line goes quiet; a simulator (or a host) paused for 60 ms
    mid-listing (seen in CI under load: rrss cut after "move") must not cut it short."""
    async with s_line(tmp_path) as line:
        tap = line.tap
        armed = threading.Event()
        armed.set()

        def pause_mid_listing(byte: int, out: bytes) -> bytes:
            if armed.is_set() and b"move" in out:
                armed.clear()
                cut = out.index(b"move")
                tap.send_late(out[cut:], 0.06)
                return out[:cut]
            return out

        tap.rewrite = pause_mid_listing
        _, lines = await line.axis(0).console("rrss")
        assert not armed.is_set()  # the pause did happen
        names = [text.split(":")[0] for text in lines]
        for name in ("limit1", "move", "inpos", "uc"):
            assert name in names, lines


@pytest.mark.parametrize("rule", ["driver", "hub"])
async def test_a_silent_module_of_a_connected_line_is_shown_offline_and_back(
    tmp_path: Path, rule: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One module of a shared line stops answering its polls, the other answers: the
    link stays connected (its failures never come 3 in a row). ``driver``: the driver
    takes the module offline after MODULE_OFFLINE_FAILURES polls, says why, and
    probes it with a growing interval, so the other module is polled at the line's
    rate again instead of waiting out the silent one's timeouts every cycle.
    ``hub`` (the driver's rule switched off): the hub's silence rule (AXIS_SILENT_S)
    shows it offline, the backstop for any driver that keeps an axis "ok" without
    samples. Either way its answers after the fault show it ok again (found in a
    soak)."""
    from servotune.devices.slap2 import modules as slap2_modules
    from servotune.hub.state import AXIS_SILENT_S

    if rule == "hub":
        monkeypatch.setattr(slap2_modules, "MODULE_OFFLINE_FAILURES", 10**9)
    bus = Slap2Line([Slap2Module(a, eeprom_path=tmp_path / f"eeprom_{a}.json") for a in (0, 1)])
    tap = Tap(bus)
    muted = threading.Event()
    # Module 1 is selected but its transmitter stays dark: no echo, no reply.
    tap.rewrite = lambda byte, out: b"" if muted.is_set() and bus.module(1).transmitting else out
    with PtySimulator(tap, baud=19200) as sim:
        hub, link = hub_on_line(sim.path, [0, 1], tmp_path)
        await hub.start()
        try:
            await wait_for(
                lambda: (
                    all(hub.entry(a).health == "ok" for a in ("line-0", "line-1"))
                    and hub.entry("line-1").latest is not None
                ),
                10,
                "both axes ok",
            )
            muted.set()
            silent = hub.entry("line-1")
            await wait_for(lambda: silent.health == "offline", AXIS_SILENT_S + 3, "axis 1 offline")
            if rule == "hub":
                assert silent.health_message.startswith("no telemetry for ")
                assert silent.health_message.endswith(
                    " s while its link is up: the device does not answer its polls"
                )
                text = "no telemetry for"
            else:
                assert silent.health_message.startswith("module 1 does not answer: 3 exchanges")
                text = "module 1 does not answer"
            assert any(
                e.level == "warning" and e.axis == "line-1" and text in e.message
                for e in hub._events
            )
            # The other module answers throughout; the line stays connected.
            count = len([e for e in hub._events if e.axis == "line-0"])
            for _ in range(10):
                assert hub.entry("line-0").health == "ok"
                assert hub.link_status("line").state == "connected"
                await asyncio.sleep(0.1)
            assert silent.health == "offline"
            # Still sampled: about once a second while each poll of the silent module
            # waits out its timeouts (hub rule); at the line's rate for one module once
            # the driver stopped polling the silent one, but for its probes (counted
            # over 2 s: more than the 2 samples a second the hub rule leaves).
            before = hub.entry("line-0").latest
            await wait_for(lambda: hub.entry("line-0").latest is not before, 2.5, "axis 0")
            if rule == "driver":
                await asyncio.sleep(2.0)
                times = link.module_state(0).samples
                recent = [t for t in times if t > times[-1] - 2.0]
                print(f"axis 0: {len(recent)} samples in 2 s with module 1 silent")
                assert len(recent) > 10, f"{len(recent)} samples of axis 0 in 2 s"
                # A failed probe keeps saying why it is offline, for how long, and when
                # it is tried next (not the bare timeout of the probe).
                assert re.fullmatch(
                    r"module 1 offline for \d+ s, does not answer \(.+\); next try in \d+ s",
                    silent.health_message,
                ), silent.health_message
            assert len([e for e in hub._events if e.axis == "line-0"]) == count
            muted.clear()
            await wait_for(lambda: silent.health == "ok", 10, "axis 1 back to ok")
            assert silent.health_message == ""
            back = "telemetry again" if rule == "hub" else "module 1 answers again after"
            assert any(e.axis == "line-1" and e.message.startswith(back) for e in hub._events)
            assert hub.link_status("line").state == "connected"
        finally:
            await hub.stop()


@pytest.mark.parametrize("addresses", [[0], [0, 1]])
async def test_a_line_whose_every_module_falls_silent_is_shown_in_error(
    tmp_path: Path, addresses: list[int]
) -> None:
    """When no module answers, the line is down: the link goes to ``error`` by the
    line's rule, and no module is taken offline by the per-module rule, whose
    message ("... while the line's other modules answered") would be false and would
    leave the link shown connected. Verify reads run every cycle here
    (``verify_period_s`` short), so failed verify reads fall between failed polls:
    counting them as "another module answered", the first version of the rule took
    a one-module line's module offline and left the link connected (review)."""
    bus = Slap2Line([Slap2Module(a, eeprom_path=tmp_path / f"eeprom_{a}.json") for a in addresses])
    tap = Tap(bus)
    muted = threading.Event()
    tap.rewrite = lambda byte, out: b"" if muted.is_set() else out
    with PtySimulator(tap, baud=19200) as sim:
        hub, link = hub_on_line(sim.path, addresses, tmp_path, verify_period_s=0.05)
        await hub.start()
        try:
            axes = [f"line-{a}" for a in addresses]
            await wait_for(
                lambda: all(hub.entry(a).latest is not None for a in axes), 10, "samples"
            )
            muted.set()
            await wait_for(lambda: hub.link_status("line").state == "error", 10, "line error")
            false_rule = [
                e.message
                for e in hub._events
                if "other modules answered" in e.message or "offline for" in e.message
            ]
            assert not false_rule, false_rule
            for a in addresses:
                assert link.module_state(a).silent_since_s is None
        finally:
            await hub.stop()


async def test_a_line_that_answers_only_wrong_bytes_is_shown_in_error_and_back(
    tmp_path: Path,
) -> None:
    """Every byte the modules send comes back wrong (a wrong baud rate, noise): bytes
    come back, so the line's rule waits out LINE_ERROR_SPAN_S (a burst after one
    stall is no error), but wrong bytes that persist are: ``error`` naming the echo
    mismatch, and connected again with samples once the bytes are right."""
    bus = Slap2Line([Slap2Module(a, eeprom_path=tmp_path / f"eeprom_{a}.json") for a in (0, 1)])
    tap = Tap(bus)
    garbled = threading.Event()
    tap.rewrite = lambda byte, out: bytes(b ^ 0x01 for b in out) if garbled.is_set() else out
    with PtySimulator(tap, baud=19200) as sim:
        hub, _ = hub_on_line(sim.path, [0, 1], tmp_path)
        await hub.start()
        try:
            await wait_for(lambda: hub.entry("line-0").latest is not None, 10, "samples")
            # The link's status carries the share of time its line was busy.
            await wait_for(lambda: (hub.link_status("line").wire_busy or 0) > 0, 5, "wire busy")
            assert (hub.link_status("line").wire_busy or 0) <= 1
            garbled.set()
            await wait_for(lambda: hub.link_status("line").state == "error", 10, "line error")
            assert "echo mismatch" in hub.link_status("line").message
            garbled.clear()
            await wait_for(lambda: hub.link_status("line").state == "connected", 15, "back")
            before = hub.entry("line-0").last_sample_at
            await wait_for(lambda: hub.entry("line-0").last_sample_at > before, 10, "samples")
        finally:
            await hub.stop()


class _MuteCrOf:
    """A ``Tap.rewrite`` that swallows everything the device sends in answer to the CR
    of the next ``line`` typed (its CR echo and its reply): the module executed the
    line, the host never hears so."""

    def __init__(self) -> None:
        self.typed = bytearray()
        self.armed: str | None = None

    def __call__(self, byte: int, out: bytes) -> bytes:
        if byte != 0x0D:
            if byte >= 0x20:
                self.typed.append(byte)
            elif byte == 0x18:
                self.typed.clear()
            return out
        line = self.typed.decode("latin-1").replace(" ", "").lower()
        self.typed.clear()
        if self.armed is not None and line == self.armed:
            self.armed = None
            return b""
        return out


def _lines(received: bytes) -> list[str]:
    return [
        part.decode("latin-1").replace(" ", "").lower().split("\x18")[-1]
        for part in received.split(b"\r")
    ]


async def test_a_command_whose_cr_echo_failed_is_not_sent_again_a_stop_is(
    tmp_path: Path,
) -> None:
    """Pinned rule: once CR has gone out the module may have executed the
    line, so a command whose CR echo (and reply) never came is not sent again: ``mr``
    twice would move the axis twice as far. ``st`` may run twice and must reach the
    module: a STOP whose CR echo was lost is sent again."""
    bus = Slap2Line([Slap2Module(0, eeprom_path=tmp_path / "eeprom_0.json")])
    tap = Tap(bus)
    mute = _MuteCrOf()
    tap.rewrite = mute
    with PtySimulator(tap, baud=19200) as sim:
        hub, _ = hub_on_line(sim.path, [0], tmp_path)
        await hub.start()
        try:
            await wait_for(lambda: hub.entry("line-0").latest is not None, 10, "samples")
            await hub.command("line-0", "position_mode", {})
            start = bus.module(0).position
            mark = tap.mark()
            mute.armed = "mr2000"
            with pytest.raises(DriverError, match="'mr2000'"):
                await hub.command("line-0", "move_relative", {"distance": 2000})
            await asyncio.sleep(1.5)
            assert _lines(tap.since(mark)).count("mr2000") == 1, _lines(tap.since(mark))
            # It ran once: the module's target moved by 2000, not 4000.
            assert abs(bus.module(0).position - (start + 2000)) < 50, bus.module(0).position

            mark = tap.mark()
            mute.armed = "st"
            await hub.entry("line-0").driver.stop()  # answers: the second st was heard
            assert _lines(tap.since(mark)).count("st") == 2, _lines(tap.since(mark))
        finally:
            await hub.stop()
