"""Capture at the wire limit (docs/capture.md): the profile law, the focused poll on
the simulated SLAP2 line and Z1100 chip (real pseudo-terminals), the pause of the
other axes, STOP first, and the repeatability of a measured step."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import itertools
import statistics
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from servotune.bench.metrics import compute_metrics
from servotune.devices.slap2.echo import EchoLine
from servotune.devices.slap2.link import Slap2Axis, Slap2Link, Slap2LinkConfig
from servotune.devices.slap2.profile import (
    COUNTS_TICK2_PER_SA,
    COUNTS_TICK_PER_SV,
    ProfileTrack,
    TrapezoidGenerator,
    firmware_setpoint,
)
from servotune.devices.slap2.sim.demo import build_slap2_line
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.link.base import Capturer, DeviceRefusedError, DriverError, capture_of
from servotune.sim.process import SerialSimSpec, serial_sim_process
from servotune.sim.pty import PtySimulator
from servotune.transports.serial import SerialConnector
from tests.support.bench import judge_step
from tests.support.sim_lines import RunningLink, chip_line, run_link, running_simulator
from tests.support.sink import RecordingSink
from tests.support.waiting import wait_for

# What these tests measure is when samples were taken on this host: they run alone
# (scripts/test.sh, docs/architecture.md "Tests").
pytestmark = pytest.mark.host_timing


def _send(module: Slap2Module, line: str) -> None:
    for byte in line.encode() + b"\r":
        module.receive(byte)


# --- the profile law against the simulated firmware -----------------------------------


@pytest.mark.parametrize(
    ("sv", "sa", "moves"),
    [
        (2000, 1000, [("mr", 3000)]),  # a trapezoid: accelerate, cruise, brake
        (500, 50, [("mr", 400)]),  # a triangle: never reaches sv
        (65535, 65535, [("mr", -2000)]),  # the bench's position step: almost a jump
        (2000, 300, [("mr", 5000), ("ma", 1000)]),  # replanned during the move
    ],
)
def test_profile_law_matches_the_firmware_tick_for_tick(
    sv: int, sa: int, moves: list[tuple[str, int]]
) -> None:
    module = Slap2Module(0)
    module.take_output()
    _send(module, f"sv{sv}")
    _send(module, f"sa{sa}")
    _send(module, "pm")
    start = module.setpoint
    generator = TrapezoidGenerator.from_wire(start, start, sv, sa)
    for index, (mnemonic, value) in enumerate(moves):
        _send(module, f"{mnemonic}{value}")
        target = value if mnemonic == "ma" else generator.target + value
        generator.replan(target, sv, sa)
        ticks = 300 if index + 1 < len(moves) else 20000
        for _ in range(ticks):
            module.tick()
            generator.step()
            # the firmware reports the rounded setpoint (pe, rp + pe)
            assert firmware_setpoint(generator.setpoint) == module.setpoint
            if not generator.moving and index + 1 == len(moves):
                break
    assert not generator.moving and generator.setpoint == generator.target
    assert module.setpoint == generator.target


def test_profile_track_maps_host_time_to_ticks() -> None:
    generator = TrapezoidGenerator.from_wire(0, 0, 2000, 1000)
    generator.replan(3000, 2000, 1000)
    track = ProfileTrack(10.0, generator)
    assert track.setpoint_at(9.0) == 0.0  # before the command: the start
    assert not track.finished_by(10.1)
    acc = 1000 * COUNTS_TICK2_PER_SA
    assert (3000 * acc) ** 0.5 < 2000 * COUNTS_TICK_PER_SV  # sv is not reached: a triangle
    expected_ticks = 2 * (3000 / acc) ** 0.5  # accelerate half way, brake the other half
    end_s = 10.0 + expected_ticks * 841.5e-6
    assert not track.finished_by(end_s - 0.01)
    assert track.finished_by(end_s + 0.01)
    assert track.setpoint_at(end_s + 1.0) == 3000.0
    mid = track.setpoint_at(10.0 + 0.5 * expected_ticks * 841.5e-6)
    assert 1400 < mid < 1600  # symmetric: half way at half time


# --- SLAP2: the focused poll on a two-module line --------------------------------------


def _axis(line: RunningLink, address: int) -> Slap2Axis:
    found = next(a for a in line.link.axes if a.address == address)
    assert isinstance(found, Slap2Axis)
    return found


async def _rate(line: RunningLink, axis_id: str, seconds: float) -> float:
    before = len(line.sink.samples[axis_id])
    await asyncio.sleep(seconds)
    return (len(line.sink.samples[axis_id]) - before) / seconds


async def test_capture_devotes_the_line_and_pauses_the_other_module(tmp_path: Path) -> None:
    with running_simulator([0, 1], tmp_path) as (simulator, bus):
        async with run_link(simulator, bus, [0, 1]) as line:
            await line.connected()
            drive = _axis(line, 1)
            assert isinstance(drive, Capturer)
            await line.until(lambda: len(line.sink.samples["line-1"]) > 3, "samples")
            normal = await _rate(line, "line-1", 1.5)
            async with capture_of(drive, "test"):
                assert line.sink.health["line-0"] == ("paused", "paused: capture on #1")
                await asyncio.sleep(0.3)  # the poll in flight ends
                paused_from = len(line.sink.samples["line-0"])
                captured = await _rate(line, "line-1", 1.5)
                # only rp (and rss at its low rate: the module is not in pm, no pe)
                stats = line.link.capture_stats(1)
                assert stats is not None and stats.samples > 0
                assert len(line.sink.samples["line-0"]) == paused_from
                sample = line.sink.samples["line-1"][-1]
                assert sample.channels["following_error"] is None  # not in pm: no pe
            assert line.sink.health["line-0"] == ("ok", "")
            await line.until(
                lambda: len(line.sink.samples["line-0"]) > paused_from + 2, "module 0 resumes"
            )
            print(f"\nline-1: {normal:.1f} samples/s polled, {captured:.1f} captured")
            # one rp per sample instead of rp, pe, rss and se for both modules
            assert captured >= 3 * normal
            assert line.link.capture_stats(1) is stats and stats.ended_s is not None


async def test_stop_during_capture_goes_first(tmp_path: Path) -> None:
    with running_simulator([0, 1], tmp_path) as (simulator, bus):
        async with run_link(simulator, bus, [0, 1]) as line:
            await line.connected()
            drive = _axis(line, 1)
            await drive.command("position_mode", {})
            async with drive.capture("test"):
                queued = [
                    asyncio.ensure_future(drive.write_params({"kd": 80 + i})) for i in range(6)
                ]
                await asyncio.sleep(0)
                stop = asyncio.ensure_future(drive.stop())
                await stop
                # at most the transaction on the wire (and the write it belongs to) before it
                done = sum(1 for job in queued if job.done())
                assert done <= 1
                await asyncio.gather(*queued)
                # The stop reached it: STOP in pm is st + pm, so the module
                # was switched off and holds again where the shaft stood.
                assert bus.module(1).rss & (1 << 3) and not bus.module(1).rss & (1 << 4)


async def test_captured_move_carries_the_reconstructed_setpoint(tmp_path: Path) -> None:
    with running_simulator([0, 1], tmp_path) as (simulator, bus):
        async with run_link(simulator, bus, [0, 1]) as line:
            await line.connected()
            drive = _axis(line, 0)
            await drive.command("position_mode", {})
            # The move's profile starts from the setpoint the host has seen held in pm
            # (polls after pm): a loaded host may not have polled by a fixed time.
            await line.until(
                lambda: (
                    bool(line.sink.samples["line-0"])
                    and bool(line.sink.samples["line-0"][-1].flags["pm"])
                    and line.sink.samples["line-0"][-1].channels["setpoint"] is not None
                ),
                "the module seen holding in pm",
                timeout_s=10,
            )
            async with drive.capture("test"):
                await drive.command("move_relative", {"distance": 3000})
                start = len(line.sink.samples["line-0"])
                await line.until(
                    lambda: (
                        len(line.sink.samples["line-0"]) > start
                        and bool(line.sink.samples["line-0"][-1].flags["inpos"])
                    ),
                    "in position",
                    timeout_s=10,
                )
                await asyncio.sleep(0.3)
                stats = line.link.capture_stats(0)
            assert stats is not None
            samples = line.sink.samples["line-0"][start:]
            setpoints = [s.channels["setpoint"] for s in samples]
            assert all(sp is not None for sp in setpoints)  # every sample: reconstructed
            assert setpoints[-1] == pytest.approx(bus.module(0).setpoint)
            # monotone towards the target (a trapezoid), each sample its own value
            values = [float(sp) for sp in setpoints if sp is not None]
            assert all(b >= a for a, b in itertools.pairwise(values))
            assert len(set(values)) > 10
            for s in samples:
                fe = s.channels["following_error"]
                assert fe == pytest.approx(
                    (s.channels["setpoint"] or 0) - (s.channels["position"] or 0)
                )
            # checked against the measured pe, and it held
            assert stats.setpoint_checks >= 3
            assert stats.setpoint_mismatches == 0, stats


# --- when a sample was taken ----------------------------------------------------------


class _LineClock:
    """A ``SimDevice`` in front of the simulated bus that records, for every line the
    host sends, the simulation time its CR reached the modules: when they act on it
    (the simulator delivers each byte at its arrival time)."""

    def __init__(self, device: Slap2Line) -> None:
        self.device = device
        self.t_s = 0.0
        self.pending = bytearray()
        self.lines: list[tuple[float, str]] = []

    def advance_to(self, t_s: float) -> bytes:
        self.t_s = max(self.t_s, t_s)
        return self.device.advance_to(t_s)

    def receive(self, byte: int) -> bytes:
        if byte == 13:
            self.lines.append((self.t_s, self.pending.decode("ascii", "replace")))
            self.pending.clear()
        elif byte >= 32:
            self.pending.append(byte)
        return self.device.receive(byte)


@contextlib.contextmanager
def _recorded_line(tmp_path: Path) -> Iterator[tuple[_LineClock, PtySimulator, Slap2Line]]:
    """Two simulated modules on a pty behind a ``_LineClock`` that records every line."""
    bus = Slap2Line([Slap2Module(a, eeprom_path=tmp_path / f"eeprom_{a}.json") for a in (0, 1)])
    clock = _LineClock(bus)
    simulator = PtySimulator(clock, baud=19200)
    simulator.start()
    try:
        yield clock, simulator, bus
    finally:
        simulator.stop()


async def test_latch_estimates_match_when_the_simulator_acted(tmp_path: Path) -> None:
    """Every captured sample's time and the move's ``last_command_latch_s`` against the
    moment the simulated module received the command's CR. The estimate is built
    from upper bounds (clock readings after the bytes arrived), so it is never early
    by more than the simulator's write margin (a quarter character); on the median it
    is within one character (the time the reply was parsed would be late by the
    reply's length, three characters and more for rp)."""
    with _recorded_line(tmp_path) as (clock, simulator, bus):
        async with run_link(simulator, bus, [0, 1]) as line:
            await line.connected()
            drive = _axis(line, 0)
            await drive.command("position_mode", {})
            await asyncio.sleep(0.2)
            async with drive.capture("test"):
                await asyncio.sleep(0.1)
                start = len(line.sink.samples["line-0"])
                await drive.command("move_relative", {"distance": 1500})
                t_move = drive.last_command_latch_s
                await asyncio.sleep(0.8)
                samples = line.sink.samples["line-0"][start:]
        # simulation time 0 is the simulator's epoch on the host's monotonic clock
        epoch = simulator._epoch  # the test's only window into simulation time
    char_s = 10 / 19200
    # Only module 0 is polled during the capture: after the move, its k-th rp is the
    # k-th sample (paired in order, so a late estimate cannot pass for a nearer read).
    (i_mr,) = [i for i, (_, text) in enumerate(clock.lines) if text == "mr1500"]
    t_mr = epoch + clock.lines[i_mr][0]
    rp_times = [epoch + t for t, text in clock.lines[i_mr:] if text == "rp"]
    assert t_move is not None
    after = [s for s in samples if s.t > t_move]
    errors = [s.t - t for s, t in zip(after, rp_times, strict=False)]
    errors.append(t_move - t_mr)
    print(
        f"\nlatch estimate - CR reached the module over {len(errors)} reads: median "
        f"{statistics.median(errors) * 1e3:.2f} ms, min {min(errors) * 1e3:.2f} ms, "
        f"p95 {statistics.quantiles(errors, n=20)[-1] * 1e3:.2f} ms, "
        f"max {max(errors) * 1e3:.2f} ms"
    )
    assert len(after) > 20
    assert min(errors) >= -char_s / 4 - 1e-4
    assert abs(statistics.median(errors)) <= char_s


class _StallOnce:
    """A host stall, injected on the wire (``PtySimulator.stall_host``): the output of the
    first ``rp`` whose CR reaches the module ``after_s`` or more (simulation time) after
    the CR of an ``mr`` is held back ``hold_s`` — the module latched on time, the host
    reads echo and reply late, exactly as if its event loop had stalled right after
    writing that CR. Bytes, not the machine's speed, decide which read it hits."""

    def __init__(self, clock: _LineClock, after_s: float, hold_s: float) -> None:
        self.clock = clock
        self.after_s = after_s
        self.hold_s = hold_s
        self.t_move: float | None = None
        self.held_at: float | None = None  # simulation time of the held rp's CR

    def delay(self, byte: int) -> float:
        # (Called on the simulator's thread after the clock advanced to the byte's
        # arrival and before the byte is delivered: ``pending`` is the line so far.)
        if byte != 13:
            return 0.0
        text = self.clock.pending.decode("ascii", "replace")
        if text.startswith("mr"):
            self.t_move = self.clock.t_s
        elif (
            text == "rp"
            and self.held_at is None
            and self.t_move is not None
            and self.clock.t_s - self.t_move >= self.after_s
        ):
            self.held_at = self.clock.t_s
            return self.hold_s
        return 0.0


async def test_a_stalled_read_leaves_no_trusted_late_settling_time(tmp_path: Path) -> None:
    """A host stall between the CR of an ``rp`` in the ringing and the read of its reply
    stamps a position from before the stall after it: the last sample outside the 2 %
    band then sits ~0.1 s late and the settling time with it (0.256 s instead of
    0.125 s was left trusted in a loaded CI run). The driver knows how early that
    latch may lie (``Sample.t_span_s``); the bench's judgement, given the spans, must
    not vouch for that settling time. The stall is injected on the wire
    (``_StallOnce``), so it hits the same read on any machine."""
    bus = build_slap2_line(tmp_path)
    clock = _LineClock(bus)
    simulator = PtySimulator(clock, baud=19200)
    simulator.start()
    stall = _StallOnce(clock, after_s=0.08, hold_s=0.1)
    try:
        async with run_link(simulator, bus, [0, 1]) as line:
            await line.connected()
            drive = _axis(line, 0)
            await drive.write_params({"velocity": 65535, "acceleration": 65535})
            await drive.command("position_mode", {})
            await asyncio.sleep(0.3)
            async with drive.capture("stall"):
                await asyncio.sleep(0.3)
                y0 = float(line.sink.samples["line-0"][-1].channels["setpoint"] or 0)
                simulator.stall_host(stall)  # type: ignore[arg-type]
                start = len(line.sink.samples["line-0"])
                await drive.command("move_relative", {"distance": 2000})
                t0 = drive.last_command_latch_s
                assert t0 is not None
                await asyncio.sleep(0.8)
                samples = [s for s in line.sink.samples["line-0"][start:] if s.t > t0]
            simulator.stall_host(None)
        epoch = simulator._epoch  # the test's only window into simulation time
    finally:
        simulator.stop()
    assert stall.held_at is not None, "the stall was not injected"
    times = [s.t for s in samples]
    positions = [float(s.channels["position"] or 0) for s in samples]
    held = max(range(len(samples)), key=lambda i: samples[i].t_span_s or 0.0)
    # The held read: stamped after the stall, and its span says how early it may lie.
    assert (samples[held].t_span_s or 0.0) >= 0.09
    assert samples[held].t - (epoch + stall.held_at) >= 0.09
    m = compute_metrics(times, positions, t0_s=t0, y0=y0, y_final=y0 + 2000)
    assert m.band is not None and m.settling_time_s is not None
    # The premise: the held sample is the last one outside the band, so the stamped
    # record settles late (the true instant is ~0.1 s earlier).
    assert abs(positions[held] - (y0 + 2000)) > m.band, "the stall missed the ringing"
    assert m.settling_time_s >= times[held] - t0
    spans = [[s.t, s.t_span_s] for s in samples if s.t_span_s is not None]
    judged, quality, _ = judge_step(times, positions, t0_s=t0, y0=y0, step=2000, spans=spans)
    print(f"\nstamped settling {m.settling_time_s:.4f} s; judged: {quality['untrusted']}")
    assert judged["settling_time_s"] is None
    assert "before its stamp" in quality["untrusted"]["settling_time_s"]
    # Only the settling time rests on that stamp: the overshoot keeps its own rules.
    assert judged["overshoot_pct"] == m.overshoot_pct or "overshoot_pct" in quality["untrusted"]


async def test_capture_switches_ucon_on_and_restores_it(tmp_path: Path) -> None:
    """During a capture the module answers a refused command with -1UC (syscon ucon
    on), so a move is followed by rp, not by the rss that tells a refusal otherwise;
    the module's own setting (off) is back when the capture ends, and after a reset
    during the capture (syscon back from the EEPROM) ucon is switched on again."""
    ucon = 1 << 5
    bus = Slap2Line([Slap2Module(a, eeprom_path=tmp_path / f"eeprom_{a}.json") for a in (0, 1)])
    clock = _LineClock(bus)
    simulator = PtySimulator(clock, baud=19200)
    simulator.start()
    try:
        async with run_link(simulator, bus, [0, 1]) as line:
            await line.connected()
            drive = _axis(line, 0)
            module = bus.module(0)
            assert not module.settings["syscon"] & ucon
            async with drive.capture("test"):
                await line.until(lambda: bool(module.settings["syscon"] & ucon), "ucon on")
                with pytest.raises(DeviceRefusedError, match="-1UC"):
                    await drive.command("move_relative", {"distance": 500})  # not in pm
                await drive.command("position_mode", {})
                await asyncio.sleep(0.1)
                sent = len(clock.lines)
                await drive.command("move_relative", {"distance": 500})
                await asyncio.sleep(0.1)
                after_move = [text for _, text in clock.lines[sent:]]
                # the banner: a reset, syscon from the EEPROM
                simulator.call(lambda: bus.power_cycle(0))
                await line.until(lambda: line.sink.health["line-0"][0] == "reset", "reset")
                await line.until(lambda: bool(module.settings["syscon"] & ucon), "ucon again")
            await line.until(lambda: not module.settings["syscon"] & ucon, "ucon restored")
            await line.until(lambda: not line.link.module_state(0).ucon, "ucon off known")
            await asyncio.sleep(0.3)
            assert not module.settings["syscon"] & ucon
            assert line.link.module_state(0).known["syscon"] == module.settings["syscon"]
    finally:
        simulator.stop()
    i = after_move.index("mr500")  # (an rp may have been on the wire before it)
    assert after_move[i + 1] == "rp", after_move[: i + 4]


# --- repeatability: a property of the measurement ---------------------------------------


async def test_five_identical_steps_measure_the_same(tmp_path: Path) -> None:
    """Five position steps with the same gains on the demo's unloaded plant (about 22 %
    overshoot with the factory gains): overshoot within 1 percentage point, settling
    within 2 sample periods. The samples of a captured axis are dense and stamped at
    their latch moment, and the peak is refined by a spline through them, so the
    metrics no longer depend on which sample caught the peak. The simulator runs in a
    process of its own, as in the demo (in this process it would share the interpreter
    with the driver: host stalls, not the measurement)."""
    spec = SerialSimSpec("slap2", functools.partial(build_slap2_line, tmp_path), 19200)
    with serial_sim_process(spec) as simulator:
        path = simulator.ready["path"]
        sink = RecordingSink()
        config = Slap2LinkConfig(link_id="line", path=path, addresses=[0, 1])
        link = Slap2Link(config, SerialConnector(path, 19200), sink)
        task = asyncio.create_task(link.run())
        try:
            await wait_for(lambda: link.state == "connected", 30, "the link")
            drive = next(a for a in link.axes if a.address == 0)
            assert isinstance(drive, Slap2Axis)
            await drive.write_params({"velocity": 65535, "acceleration": 65535})
            await drive.command("position_mode", {})
            # latch time of the last command that moved the axis (pm, the way back)
            t_back = drive.last_command_latch_s
            assert t_back is not None
            results = []
            disturbed = 0
            warm_up = True
            while len(results) < 5 and disturbed < 60:
                await asyncio.sleep(0.3)
                async with drive.capture("repeatability"):
                    await asyncio.sleep(0.1)
                    latest = None
                    for _ in range(100):  # at rest before each step (at most 2 s)
                        # ... in a sample latched since the way back: a starved host
                        # delivers none for a while, and the last one before shows the
                        # previous step's end (its setpoint taken for y0 once made the
                        # record a 0 % "overshoot" that never settled, and walked the
                        # axis 2000 counts from its start)
                        sample = sink.samples["line-0"][-1]
                        setpoint = sample.channels["setpoint"]
                        position = sample.channels["position"]
                        if (
                            sample.t > t_back
                            and sample.flags["inpos"]
                            and not sample.flags["move"]
                            and setpoint is not None
                            and position is not None
                            and abs(position - setpoint) <= 5  # the in-position window
                        ):
                            latest = sample
                            break
                        await asyncio.sleep(0.02)
                    if latest is None:
                        disturbed += 1
                        continue
                    y0 = float(latest.channels["setpoint"] or 0)
                    start = len(sink.samples["line-0"])
                    try:
                        await drive.command("move_relative", {"distance": 2000})
                    except DriverError:
                        # a stalled host desynchronised the line (the driver says so
                        # and resynchronises): not a measurement of the axis (which
                        # may have moved: the next rest is judged on newer samples)
                        disturbed += 1
                        t_back = max(t_back, sink.samples["line-0"][-1].t)
                        continue
                    t0 = drive.last_command_latch_s
                    assert t0 is not None
                    await asyncio.sleep(0.6)
                # By latch time, not by what had arrived when this task resumed after
                # the command: on a loaded host it may resume after the rise and the
                # peak (a record of the ringing only, 0.15 % "overshoot", was seen).
                samples = [s for s in sink.samples["line-0"][start:] if s.t > t0]
                # back to the start (not recorded): the steps never walk into E2
                try:
                    await drive.command("move_absolute", {"position": round(y0)})
                except DriverError:
                    # a host stalled past the echo timeout: the driver says it cannot
                    # tell whether the module took the move; the next run starts from
                    # wherever the axis is
                    disturbed += 1
                    t_back = max(t_back, sink.samples["line-0"][-1].t)
                    continue
                t_back = drive.last_command_latch_s or t_back
                times = [s.t for s in samples]
                positions = [float(s.channels["position"] or 0) for s in samples]
                period = statistics.median(b - a for a, b in itertools.pairwise(times))
                # A host that stalls the driver (a loaded machine) reads replies late:
                # the bench's own judgement (bench.quality: a stamp followed by a shorter
                # gap than usual was late; a settling instant located by a sample the
                # driver may have latched long before its stamp, its t_span_s: one
                # 0.256 s among 0.125 s was so) nulls the metrics it cannot trust, and such
                # a run is taken again, as a user would (at most 60 times). A host too
                # slow to keep the wire busy paces the whole record instead (every stamp
                # late by a varying part of its delay; 21.0 and 22.9 % were read at a
                # 10.4 ms period): a median period over 1.4 times the wire time of an rp
                # (11 characters, 5.7 ms) is the host's, not the axis's.
                if period > 1.4 * 11 * 10 / 19200:
                    disturbed += 1
                    continue
                # settling into 2 % of the step (the usual definition): the +-5 counts of the
                # in-position window are grazed by a late ringing lobe, run by run
                spans = [[s.t, s.t_span_s] for s in samples if s.t_span_s is not None]
                judged, quality, _ = judge_step(
                    times, positions, t0_s=t0, y0=y0, step=2000, spans=spans
                )
                assert judged is not None and quality["status"] != "bad", quality
                if judged["overshoot_pct"] is None or judged["settling_time_s"] is None:
                    print("retaken:", quality["untrusted"])
                    disturbed += 1
                    continue
                if warm_up:
                    # The first step after pm is switched on starts from another state
                    # of the controller (its integrator): a different experiment.
                    warm_up = False
                    continue
                results.append(
                    (judged["overshoot_pct"], judged["settling_time_s"], period, disturbed)
                )
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
    print(
        "\n"
        + "\n".join(
            f"overshoot {o} %, settling {s} s, period {p} s, disturbed runs so far {g}"
            for o, s, p, g in results
        )
    )
    assert len(results) == 5, f"the host disturbed {disturbed} runs: too loaded to measure"
    overshoots = [r[0] for r in results]
    settlings = [r[1] for r in results]
    assert None not in overshoots and None not in settlings
    period = max(r[2] for r in results)
    assert max(overshoots) - min(overshoots) <= 1.0  # type: ignore[type-var,operator]
    assert max(settlings) - min(settlings) <= 2 * period  # type: ignore[type-var,operator]


# --- Z1100 ------------------------------------------------------------------------------


async def test_z1100_capture_polls_one_motor(tmp_path: Path) -> None:
    async with chip_line(tmp_path) as running:
        link = running.link
        motor = running.axis(1)
        await wait_for(lambda: len(running.sink.samples[link.axis_id(1)]) > 5, 10, "samples")
        normal = await _rate_z(running, 1, 1.5)
        async with capture_of(motor, "test"):
            assert running.sink.health[link.axis_id(0)][0] == "paused"
            assert running.sink.health[link.axis_id(2)] == ("paused", "paused: capture on motor 2")
            # A poll of the others may still be under way when the capture starts; once
            # the capture's own samples arrive, the wire is the capture's alone.
            captured_from = len(running.sink.samples[link.axis_id(1)])
            await wait_for(
                lambda: len(running.sink.samples[link.axis_id(1)]) >= captured_from + 3,
                10,
                "captured samples",
            )
            others = [len(running.sink.samples[link.axis_id(i)]) for i in (0, 2)]
            captured = await _rate_z(running, 1, 1.5)
            assert [len(running.sink.samples[link.axis_id(i)]) for i in (0, 2)] == others
            recent = running.sink.samples[link.axis_id(1)][-30:]
            errors = [s.channels["following_error"] for s in recent]
            fresh = [e for e in errors if e is not None]
            # GetError every few samples: a slow channel, never stale next to fresh rp
            assert 0 < len(fresh) < len(errors)
        assert running.sink.health[link.axis_id(0)] == ("ok", "")
        print(f"\nmotor 2: {normal:.1f} samples/s polled, {captured:.1f} captured")
        # GetEncoder (+ GetError every 6th at rest) instead of both for three motors
        assert captured >= 3 * normal


async def _rate_z(running: object, index: int, seconds: float) -> float:
    link = running.link  # type: ignore[attr-defined]
    samples = running.sink.samples[link.axis_id(index)]  # type: ignore[attr-defined]
    before = len(samples)
    await asyncio.sleep(seconds)
    return (len(samples) - before) / seconds


async def test_polls_chain_their_next_read_and_keep_the_wire_order(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The poll loop hands the channel the read it makes next (rp -> pe -> rss of a
    module; in a capture rp -> rp), so the port's callback can send it right after
    the reply (devices/slap2/echo.py, EchoLine.transact). What the modules receive is
    the same sequence as without it, no chained read is wasted while nothing else
    runs, and a STOP in between still reaches the wire."""
    chained: list[tuple[bytes, bytes]] = []
    original = EchoLine.transact

    async def spy(self: EchoLine, data: bytes, *args: Any, **kwargs: Any) -> Any:
        chained.append((data, kwargs.get("then", b"")))
        return await original(self, data, *args, **kwargs)

    monkeypatch.setattr(EchoLine, "transact", spy)
    with _recorded_line(tmp_path) as (clock, simulator, bus):
        async with run_link(simulator, bus, [0, 1]) as line:
            await line.connected()
            await asyncio.sleep(1.0)
            assert line.link.counters["chained_reads_dropped"] == 0
            assert (b"rp\r", b"pe\r") in chained and (b"pe\r", b"rss\r") in chained
            polled = [text for _, text in clock.lines if text in ("rp", "pe", "rss")]
            start = polled.index("rp")
            cycle = polled[start : start + 3 * (len(polled[start:]) // 3)]
            assert cycle == ["rp", "pe", "rss"] * (len(cycle) // 3), cycle
            drive = _axis(line, 0)
            await drive.command("position_mode", {})
            async with drive.capture("test"):
                await asyncio.sleep(0.5)
                assert (b"rp\r", b"rp\r") in chained
                before = len(clock.lines)
                await drive.stop()
                assert "st" in [text for _, text in clock.lines[before:]]
            samples = line.sink.samples["line-0"]
            assert samples and all(s.channels["position"] is not None for s in samples)
