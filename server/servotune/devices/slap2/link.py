"""The SLAP2 link: one RS232 line and what is known of its modules.

One ``Slap2Link`` owns one RS232 line with up to 16 modules (multi-drop). Its owner
task is the only code that touches the port; everything else submits *jobs*. Between
two wire transactions the owner takes, in this order: a stop job, a user job, the
next poll transaction. A stop therefore waits at most for the one transaction in
flight (a few ms at 19200 baud), never for queued polls or commands.

The split: the link *has* a ``LinkEngine`` (link/engine.py: owner task, job queues,
reconnects, status), for which it is the ``LinkSession``, and a ``Slap2Exchange``
(devices/slap2/exchange.py), which does the exchange on the line. This module owns
what is known of each module (online, reset evidence, parameters, the profile of its
last move: ``ModuleBook``, devices/slap2/modules.py), the session loop, polling and
capture scheduling.

The exchange's rules are in devices/slap2/exchange.py. Decisions of the link where the
manual is silent (also in docs/slap2.md):

* Reset evidence must survive a slow host: a weak cue makes a module *suspect*, and
  only a check that confirms it flags ``reset`` (``devices/slap2/modules.py``).
* Refusal: ``-1UC`` (syscon ``ucon`` set) or, when ``ucon`` is off, the ``uc`` bit of
  an ``rss`` read right after the command.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

from servotune.descriptor import DeviceDescriptor
from servotune.devices.slap2 import codec
from servotune.devices.slap2.axis import Slap2Axis
from servotune.devices.slap2.capture import (
    CAPTURE_UCON,
    CHECK_TOLERANCE_COUNTS,
    MISSES_TO_DROP,
    MOVE_MNEMONICS,
    ModuleCapture,
)
from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.devices.slap2.exchange import (
    Slap2Exchange,
    command_mnemonic,
    is_banner,
)
from servotune.devices.slap2.modules import ModuleBook, ModuleState
from servotune.devices.slap2.profile import TICK_S, firmware_setpoint
from servotune.link.base import (
    AxisDriver,
    DeviceRefusedError,
    DriverError,
    DriverSink,
    InvalidArgumentError,
    Sample,
    check_console_line,
)
from servotune.link.capture import CaptureRegistry, CaptureStats
from servotune.link.engine import LinkEngine, engine_face, recent_rate_hz
from servotune.link.setpoint import STEADY_ERROR_COUNTS
from servotune.transports.base import ByteChannel, Connector

logger = logging.getLogger(__name__)

# Outside a capture pe is read one transaction after rp (~6 ms at 19200 baud): what the
# profile moves in that time is allowed in the live check of the reconstruction.
LIVE_SKEW_S = 0.01

T = TypeVar("T")

# Tries of switching syscon ucon for a capture (or back) before doing without.
UCON_ATTEMPTS = 3


@dataclass(slots=True)
class Slap2LinkConfig:
    """Settings of one SLAP2 line. Times are deliberately below the manual's 200 ms."""

    link_id: str
    path: str
    addresses: list[int]
    baud: int = codec.DEFAULT_BAUD
    lines: int = 512
    names: dict[int, str] = field(default_factory=dict)
    char_timeout_s: float = 0.15
    quiet_s: float = 0.03
    # A listing (rrss, rrsyscon, rep) ends when the line goes quiet (the manual's rule):
    # longer than ``quiet_s`` (which ends every other console reply), because a listing
    # is asked for by a person, who does not feel 100 ms more, and a short pause of a
    # busy host or simulator must not cut it short.
    listing_quiet_s: float = 0.1
    banner_quiet_s: float = 0.25
    banner_max_s: float = 2.0
    poll_commands: tuple[str, ...] = ("rp", "pe", "rss")
    rve_every: int = 8
    verify_period_s: float = 2.0
    reconnect_max_s: float = 5.0
    offline_retry_s: float = 1.0


class Slap2Link:
    """Owner of one SLAP2 RS232 line; see the module docstring for the protocol rules.

    ``link.base.Link``; the ``LinkSession`` of its ``engine`` and the
    ``ExchangeEvents`` of its ``exchange``; the link each ``Slap2Axis`` talks to."""

    device = "slap2"

    def __init__(
        self,
        config: Slap2LinkConfig,
        connector: Connector,
        sink: DriverSink,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not config.addresses:
            raise ValueError("a SLAP2 link needs at least one module address")
        self._engine = LinkEngine(
            config.link_id,
            config.path,
            config.baud,
            connector,
            sink,
            self,
            clock=clock,
            reconnect_max_s=config.reconnect_max_s,
        )
        self._exchange = Slap2Exchange(config, self._engine, self)
        self._connector = connector
        self._sink = sink
        self._clock = clock
        self.config = config
        self._descriptor = slap2_descriptor(config.lines)
        self._captures = CaptureRegistry(self._capture_changed)
        self._book = ModuleBook(
            config.addresses,
            self._engine,
            self._exchange,
            self._descriptor,
            self._captures,
            char_timeout_s=config.char_timeout_s,
            offline_retry_s=config.offline_retry_s,
        )
        self._modules = self._book.modules
        self._axes: list[AxisDriver] = [Slap2Axis(self, a) for a in config.addresses]
        self._poll_index = 0
        self._last_verify_t = 0.0
        self._capture_index = 0

    # --- its parts, its axes -----------------------------------------------------------

    @property
    def engine(self) -> LinkEngine:
        """The owner task, job queues and status of this line."""
        return self._engine

    @property
    def exchange(self) -> Slap2Exchange:
        """The manual's exchange on this line (owner task only)."""
        return self._exchange

    @property
    def axes(self) -> list[AxisDriver]:
        return list(self._axes)

    @property
    def descriptor(self) -> DeviceDescriptor:
        """The descriptor all axes of this line share."""
        return self._descriptor

    # link.base.Link (with HasCounters, HasWireBusy, WireStats): the engine's members.
    id, path, baud, state, errors, counters, wire_busy, now, run = engine_face()

    @property
    def modules(self) -> ModuleBook:
        """What is known of each module, and the rules that change it (owner task)."""
        return self._book

    def axis_id(self, address: int) -> str:
        return self._book.axis_id(address)

    def axis_name(self, address: int) -> str:
        return self.config.names.get(address, f"SLAP2 #{address}")

    def module_state(self, address: int) -> ModuleState:
        return self._modules[address]

    def link_down(self) -> None:
        self._book.link_down()

    # --- session ---------------------------------------------------------------------

    async def run_session(self, channel: ByteChannel) -> None:
        self._exchange.forget_selection()
        self._engine.set_state("connecting", f"draining power-on output on {self.path}")
        banner = await self._exchange.drain(
            channel, self.config.banner_quiet_s, self.config.banner_max_s
        )
        if banner.strip():
            text = codec.LineDecoder().feed(banner + b"\r")
            self._sink.on_event("info", None, f"{self.id}: power-on banner: {' | '.join(text)}")
        for module in self._modules.values():
            await self._book.probe(module)
        self._engine.connected_once = True
        self._engine.set_state("connected", self._connector.description)
        while True:
            job = self._engine.take_job()
            if job is not None:
                await self._engine.run_job(job)
                continue
            now = self._clock()
            online = [m for m in self._modules.values() if m.online]
            if not online:
                await self._engine.wait_job_or(self.config.offline_retry_s)
                if not self._engine.jobs_pending:
                    for module in self._modules.values():
                        await self._book.probe(module)
                continue
            restore = next((m for m in online if m.ucon_restore and m.capture is None), None)
            if restore is not None:
                await self._switch_ucon(restore, on=False)
                continue
            captured = [m for m in online if m.capture is not None]
            if captured:
                # The line is devoted to the captured module(s): no verify reads, no
                # probes, the others pause (devices/slap2/capture.py).
                suspect = next((m for m in captured if m.suspect), None)
                if suspect is not None:
                    await self._book.confirm_suspect(suspect)
                    continue
                await self._capture_step(captured)
                continue
            suspect = next((m for m in online if m.suspect), None)
            if suspect is not None:
                await self._book.confirm_suspect(suspect)
                continue
            if now - self._last_verify_t >= self.config.verify_period_s:
                self._last_verify_t = now
                await self._book.verify(online[self._poll_index % len(online)])
                continue
            await self._poll_step(online)
            due = [m for m in self._modules.values() if not m.online and now >= m.next_probe_t]
            if due and not self._engine.jobs_pending:
                # Retry absent modules with a growing interval: each try holds the line
                # for a few character timeouts, which must not starve the others or
                # delay a STOP more than once in a while.
                module = due[0]
                module.probe_interval_s = min(
                    max(module.probe_interval_s * 2, self.config.offline_retry_s), 30.0
                )
                module.next_probe_t = now + module.probe_interval_s
                await self._book.probe(module)

    # --- ExchangeEvents: what only the module book can judge ---------------------------

    def note_unsolicited(self, data: bytes) -> None:
        self._book.note_unsolicited(data)

    def lost_selection(self, address: int) -> None:
        self._book.lost_selection(address)

    # --- polling ----------------------------------------------------------------------

    async def _poll_step(self, online: list[ModuleState]) -> None:
        """Poll one module completely (rp, pe, rss; rve every n-th cycle)."""
        module = online[self._poll_index % len(online)]
        self._poll_index += 1
        try:
            await self._poll_module(module)
            self._book.answered(module)
        except DriverError as exc:
            self._book.failed(module, exc)

    async def _poll_module(self, module: ModuleState) -> None:
        address = module.address
        position: int | None = None
        t_position = 0.0
        following_error: int | None = None
        rss: int | None = None
        rss_t: float | None = None
        # (Counted only when the cycle completes, so that a cut-short one keeps its rve.)
        rve_due = bool(self.config.rve_every and (module.cycles + 1) % self.config.rve_every == 0)
        sequence = [*self.config.poll_commands, *(["rve"] if rve_due else [])]
        for index, mnemonic in enumerate(sequence[: len(self.config.poll_commands)]):
            if self._engine.urgent_pending:
                # A stop is waiting: give the line up now, finish the sample later.
                return
            then = sequence[index + 1] if index + 1 < len(sequence) else None
            value = await self._exchange.read_int(address, mnemonic, then)
            if mnemonic == "rp":
                position, t_position = value, self._exchange.last_latch_t
            elif mnemonic == "pe":
                following_error = value
            elif mnemonic == "rss":
                rss, rss_t = value, self._exchange.last_latch_t
        measured: float | None = None
        module.cycles += 1
        if rve_due:
            measured = await self._exchange.read_int(address, "rve") * codec.COUNTS_S_PER_SV
        if self._engine.state == "error":
            self._engine.set_state("connected", self._connector.description)
        self._emit_sample(module, position, t_position, following_error, rss, rss_t, measured)

    def _emit_sample(
        self,
        module: ModuleState,
        position: int | None,
        t_position: float,
        following_error: int | None,
        rss: int | None,
        rss_t: float | None,
        measured: float | None,
    ) -> None:
        t = t_position or self._clock()
        if position is not None:
            if module.position is not None and module.position_t is not None:
                dt = t - module.position_t
                if dt > 0:
                    module.velocity = (position - module.position) / dt
            module.position, module.position_t = position, t
        if following_error is not None:
            module.following_error = following_error
        if rss is not None:
            self._book.check_rss(module, rss)
            module.rss, module.rss_t = rss, rss_t
        flags = codec.decode_rss(module.rss or 0)
        # The setpoint: the reconstructed profile where the driver knows it; else rp +
        # pe, two reads a transaction apart, only while pe is steady (drivers.setpoint).
        skewed = module.skewed.setpoint(
            module.position, following_error, profile_running=flags["move"]
        )
        reconstructed = self._live_setpoint(module, flags, t, skewed)
        setpoint: float | None
        error: float | None
        if reconstructed is not None and module.position is not None:
            setpoint = round(reconstructed, 2)
            error = round(setpoint - module.position, 2)
        else:
            setpoint, error = skewed, module.following_error
        channels: dict[str, float | None] = {
            "position": module.position,
            "setpoint": setpoint,
            "following_error": error,
            "velocity": module.velocity,
            "velocity_measured": measured,
        }
        module.samples.append(t)
        self._sink.on_sample(
            self.axis_id(module.address), Sample(t, channels, flags, flags_t=module.rss_t)
        )

    def _live_setpoint(
        self, module: ModuleState, flags: Mapping[str, bool], t: float, skewed: float | None
    ) -> float | None:
        """The reconstructed profile at ``t`` outside a capture, checked where rp + pe
        is steady (at rest, or tracking smoothly): two disagreements in a row beyond
        what the reads' skew and the tick allow (a limit switch ended the move, a
        setting changed behind servotune's back) drop it, as a capture's pe check does.
        A ringing axis is not checked (its rp + pe is no setpoint)."""
        track = module.profile.track
        if track is None or not flags["pm"]:
            return None
        reconstructed = track.setpoint_at(t)
        if skewed is None:
            return reconstructed
        tolerance = (
            CHECK_TOLERANCE_COUNTS
            + STEADY_ERROR_COUNTS
            + abs(track.setpoint_at(t + TICK_S) - track.setpoint_at(t - TICK_S))
            + abs(track.setpoint_at(t + LIVE_SKEW_S) - reconstructed)
        )
        if abs(skewed - firmware_setpoint(reconstructed)) <= tolerance:
            module.live_misses = 0
            return reconstructed
        module.live_misses += 1
        if module.live_misses < MISSES_TO_DROP:
            return reconstructed
        module.live_misses = 0
        module.profile.clear()
        self._engine.count("setpoint_mismatches")
        logger.info(
            "%s: module %d: rp + pe %.0f, the reconstructed setpoint %.0f: dropped",
            self.id,
            module.address,
            skewed,
            reconstructed,
        )
        return None

    # --- capture (drivers.base.Capturer; decisions in devices/slap2/capture.py) ---------

    def capture(self, address: int, reason: str) -> contextlib.AbstractAsyncContextManager[None]:
        """Devote the line to module ``address`` while the context is open."""
        if address not in self._modules:
            raise InvalidArgumentError("address", f"no module {address} on {self.id}")
        return self._captures.hold(address, reason)

    def capture_stats(self, address: int) -> CaptureStats | None:
        """The running capture's statistics of a module, else its last capture's."""
        module = self._modules[address]
        return module.capture.stats if module.capture is not None else module.last_capture

    def _capture_changed(self) -> None:
        captured = set(self._captures.addresses)
        now = self._clock()
        for module in self._modules.values():
            if module.address in captured and module.capture is None:
                module.capture = ModuleCapture(CaptureStats(started_s=now))
                module.ucon_failures = 0
                module.samples.clear()  # the rate restarts with the limit (see below)
            elif module.address not in captured and module.capture is not None:
                # The rate counts the samples of the last 2 s against the limit of the
                # poll set in force: the capture's dense samples, counted against the
                # normal poll set's limit, would read above 100 % of the wire.
                module.samples.clear()
                stats = module.capture.stats
                stats.ended_s = now
                module.last_capture, module.capture = stats, None
                logger.info(
                    "%s: capture of module %d ended: %d samples in %.2f s, %d setpoint "
                    "checks (%d off, max residual %.1f counts)",
                    self.id,
                    module.address,
                    stats.samples,
                    now - stats.started_s,
                    stats.setpoint_checks,
                    stats.setpoint_mismatches,
                    stats.max_setpoint_residual,
                )
            paused = bool(captured) and module.address not in captured
            if paused != module.paused:
                module.paused = paused
                if module.online:
                    on = ", ".join(f"#{a}" for a in sorted(captured))
                    self._sink.on_axis_health(
                        self.axis_id(module.address),
                        "paused" if paused else "ok",
                        f"paused: capture on {on}" if paused else "",
                    )
        self._engine.wake()

    async def _capture_step(self, captured: list[ModuleState]) -> None:
        """One sample of a captured module: ``rp``, and ``pe``/``rss`` when due."""
        module = captured[self._capture_index % len(captured)]
        self._capture_index += 1
        capture = module.capture
        assert capture is not None
        address = module.address
        if CAPTURE_UCON and not module.ucon and module.ucon_failures < UCON_ATTEMPTS:
            # (A module that keeps failing it is captured without: rss after moves.)
            await self._switch_ucon(module, on=True)
            return
        chars_before = self._exchange.wire_chars
        fresh_pe: int | None = None
        # The step's reads are planned before its rp, so that each can be chained from
        # the reply before it (see Slap2Exchange.exchange_once): pe and rss if due now, then the
        # next step's rp when that is this module's again. (Decided after the rp,
        # a pe or rss would come one step later at most.)
        alone = len(captured) == 1
        now = self._clock()
        flags_now = codec.decode_rss(module.rss or 0)
        pe_due = capture.wants_pe(module.profile, flags_now, now)
        track = module.profile.track
        window = module.known.get("inpos_window")
        rss_due = capture.wants_rss(
            module.profile,
            now,
            flags_fresh=not module.ucon,
            arrived=flags_now["inpos"],
            inside_window=(
                track is not None
                and window is not None
                and module.position is not None
                and abs(module.position - track.target) <= window
            ),
        )
        after_rss = "rp" if alone else None
        after_pe = "rss" if rss_due else after_rss
        try:
            position = await self._exchange.read_int(address, "rp", "pe" if pe_due else after_pe)
            t, t_span = self._exchange.last_latch_t, self._exchange.last_latch_span_s
            why = capture.resolve(module.profile, t, position)
            if why:
                self._engine.count("setpoint_mismatches")
                logger.info("%s: module %d: %s", self.id, address, why)
            flags = codec.decode_rss(module.rss or 0)
            if not self._engine.urgent_pending and pe_due:
                fresh_pe = await self._exchange.read_int(address, "pe", after_pe)
                capture.pending = (self._exchange.last_latch_t, fresh_pe)
                capture.last_pe_s = self._exchange.last_latch_t
                capture.samples_since_pe = 0
                module.following_error = fresh_pe
                capture.note_rest(module.profile, flags, t, position + fresh_pe)
            else:
                capture.samples_since_pe += 1
            if not self._engine.urgent_pending and rss_due:
                rss = await self._exchange.read_int(address, "rss", after_rss)
                capture.last_rss_s = self._exchange.last_latch_t
                self._book.check_rss(module, rss)
                module.rss, module.rss_t = rss, self._exchange.last_latch_t
            self._book.answered(module)
        except DriverError as exc:
            capture.stats.wire_chars += self._exchange.wire_chars - chars_before
            self._book.line_failed(exc)
            return
        capture.stats.wire_chars += self._exchange.wire_chars - chars_before
        capture.stats.samples += 1
        capture.previous = (t, position)
        if self._engine.state == "error":
            self._engine.set_state("connected", self._connector.description)
        self._emit_captured(module, t, position, fresh_pe, t_span)

    async def _switch_ucon(self, module: ModuleState, *, on: bool) -> None:
        """Switch syscon ``ucon`` on for a capture (``ssb5``) or restore it (``rsb5``).

        With ucon on a refused command answers ``-1UC``, so a move (an injection sends
        one every few samples) needs no ``rss`` after it. Switching on reads syscon
        first (after a reset the driver no longer knows it) and leaves a module that
        has ucon on by itself alone. Failures count like a failed poll; the owner loop
        tries again on its next turn.
        """
        bit = codec.SysconBit.ucon.value
        try:
            syscon = await self._exchange.read_int(module.address, "rsyscon")
            if codec.decode_syscon(syscon)["ucon"] != on:
                await self._book.execute(module, codec.make_set("ssb" if on else "rsb", bit))
                syscon = await self._exchange.read_int(module.address, "rsyscon")
                module.ucon_restore = on
        except DriverError as exc:
            self._book.line_failed(exc)
            module.ucon_failures += 1
            if not on and module.ucon_failures >= UCON_ATTEMPTS:
                # Not worth starving the line for: say so and leave it on.
                module.ucon_restore = False
                self._sink.on_event(
                    "warning",
                    self.axis_id(module.address),
                    f"module {module.address}: syscon ucon, switched on for a capture, "
                    f"could not be switched off again: {exc}",
                )
            return
        module.ucon_failures = 0
        self._book.learn_syscon(module, syscon)
        # The device's value now (a reset check must not take it for a change); the
        # restore puts the module's own setting back.
        module.known["syscon"] = syscon
        if not on:
            module.ucon_restore = module.ucon  # still on: the rsb5 did not take
        logger.info(
            "%s: module %d: syscon ucon %s (capture)",
            self.id,
            module.address,
            "on" if module.ucon else "off",
        )

    def _emit_captured(
        self,
        module: ModuleState,
        t: float,
        position: int,
        fresh_pe: int | None,
        t_span: float | None = None,
    ) -> None:
        if module.position is not None and module.position_t is not None and t > module.position_t:
            module.velocity = (position - module.position) / (t - module.position_t)
        module.position, module.position_t = position, t
        flags = codec.decode_rss(module.rss or 0)
        setpoint = module.profile.setpoint_at(t) if flags["pm"] else None
        following_error: float | None
        if setpoint is not None:
            setpoint = round(setpoint, 2)
            following_error = round(setpoint - position, 2)
        elif fresh_pe is not None:
            # No profile to trust: pe as read (a slow channel between its reads).
            following_error = fresh_pe
            setpoint = position + fresh_pe
        else:
            following_error = None
        channels: dict[str, float | None] = {
            "position": position,
            "setpoint": setpoint,
            "following_error": following_error,
            "velocity": module.velocity,
            "velocity_measured": None,
        }
        module.samples.append(t)
        self._sink.on_sample(
            self.axis_id(module.address),
            Sample(t, channels, flags, t_span_s=t_span, flags_t=module.rss_t),
        )

    # --- status -----------------------------------------------------------------------

    def wire_limit_hz(self) -> float:
        """Samples/s per axis the wire allows for the poll set, from actual reply lengths.

        Per transaction: every command char and CR is sent and echoed (2 chars each),
        then the reply and its CR: all at 10 bit times per character. During a
        capture: the limit of the captured modules' actual poll mix (rp, and pe, rss
        and se as often as they were read), from the characters they took.
        """
        char_s = 10 / self.config.baud
        captures = [m.capture for m in self._modules.values() if m.capture is not None]
        if captures:
            samples = sum(c.stats.samples for c in captures)
            chars = sum(c.stats.wire_chars for c in captures)
            if samples and chars:
                return samples / len(captures) / (chars * char_s)
            return 1 / ((2 * 3 + self._exchange.reply_chars.get("rp", 2)) * char_s * len(captures))
        online = [m for m in self._modules.values() if m.online] or list(self._modules.values())
        per_module = 0.0
        for mnemonic in self.config.poll_commands:
            reply = self._exchange.reply_chars.get(mnemonic, 2)
            per_module += 2 * (len(mnemonic) + 1) + reply
        if self.config.rve_every:
            per_module += (2 * 4 + self._exchange.reply_chars.get("rve", 2)) / self.config.rve_every
        if len(online) > 1:
            per_module += 2 * (len(f"se{online[0].address}") + 1) + 1
        cycle_s = per_module * char_s * len(online)
        return 1 / cycle_s

    def achieved_rate_hz(self) -> float:
        """Mean telemetry samples per second per online axis over the last 2 s."""
        now = self._clock()
        polled = [m for m in self._modules.values() if m.online and not m.paused]
        rates = [recent_rate_hz(m.samples, now) for m in polled]
        return sum(rates) / len(rates) if rates else 0.0

    # --- operations used by Slap2Axis -------------------------------------------------

    async def op_read_params(self, address: int) -> dict[str, int]:
        module = self._modules[address]

        async def job() -> dict[str, int]:
            return await self._book.read_params(module)

        values = await self._engine.submit(job)
        self._sink.on_params(self.axis_id(address), values, "read")
        return values

    async def op_write_params(
        self, address: int, values: Mapping[str, int], source: str
    ) -> dict[str, int]:
        module = self._modules[address]

        async def job() -> dict[str, int]:
            return await self._book.write_params(module, values)

        readback = await self._engine.submit(job)
        self._sink.on_params(self.axis_id(address), readback, source)
        return readback

    async def op_execute(
        self,
        address: int,
        commands: list[codec.Command],
        *,
        urgent: bool = False,
        stop: bool | None = None,
    ) -> list[str]:
        """Run ``commands`` on module ``address`` as one job. ``stop`` (default: the
        commands contain ``st``) fails the module's queued motion first and makes the
        job urgent (``LinkEngine.submit``)."""
        module = self._modules[address]

        async def job() -> list[str]:
            sent: list[str] = []
            for command in commands:
                await self._book.execute(module, command)
                sent.append(command.text)
                self._book.track_mode(module, command.text)
            return sent

        is_stop = any(c.text == "st" for c in commands) if stop is None else stop
        return await self._engine.submit(
            job, urgent=urgent, axis=address, motion=True, stop=is_stop
        )

    async def op_raw_byte(self, address: int, byte: int, *, urgent: bool = False) -> None:
        """Send one control character (Ctrl-K) to a module and drain its echo."""

        async def job() -> None:
            channel = self._engine.require_channel()
            if await self._exchange.settle_chain(channel):
                self._exchange.deselect()
            await self._exchange.select(address)
            await channel.write(bytes([byte]))
            await self._exchange.drain(channel, self.config.quiet_s, 0.2)

        await self._engine.submit(job, urgent=urgent)

    async def op_console(self, address: int, line: str) -> tuple[str, list[str]]:
        module = self._modules[address]
        check_console_line(line)
        try:
            text = codec.normalise_line(line)
        except codec.CodecError as exc:
            raise InvalidArgumentError("line", str(exc)) from None
        mnemonic = command_mnemonic(text)
        if mnemonic == "se":
            raise InvalidArgumentError(
                "line", "se is managed by servotune: pick the module in the navigation"
            )
        command = codec.Command(text, multiline=True)

        async def job() -> list[str]:
            if mnemonic in MOVE_MNEMONICS:
                module.profile.clear()  # a console move is not reconstructed
            lines = await self._exchange.transact(address, command)
            if lines and codec.parse_reply(lines[0]).kind is codec.ReplyKind.REFUSED:
                raise DeviceRefusedError(f"{text}: refused by the module (-1UC)")
            if not module.ucon and mnemonic not in ("rss", "ss", "rrss"):
                # Without ucon a refusal is a bare CR: the uc flag tells (rss leaves it).
                rss = await self._exchange.read_rss_after(text)
                if codec.decode_rss(rss)["uc"]:
                    raise DeviceRefusedError(
                        f"{text}: refused by the module (uc flag set: unknown command, "
                        "bad argument, or not allowed in this mode)"
                    )
            self._book.track_mode(module, text)
            if mnemonic == "ssyscon" or mnemonic in ("ssb", "rsb"):
                module.known.pop("syscon", None)
                module.ucon_restore = False  # the user's setting now: nothing to restore
                self._book.learn_syscon(module, await self._exchange.read_int(address, "rsyscon"))
            return lines

        # A raw line may move the axis (vm, ma, spwm ...): a STOP discards it too.
        return text, await self._engine.submit(
            job, axis=address, motion=True, stop=mnemonic == "st"
        )


__all__ = ["Slap2Axis", "Slap2Link", "Slap2LinkConfig", "is_banner"]
