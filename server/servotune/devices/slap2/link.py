"""SLAP2 link engine and axis driver.

One ``Slap2Link`` owns one RS232 line with up to 16 modules (multi-drop). Its owner
task is the only code that touches the port; everything else submits *jobs*. Between
two wire transactions the owner takes, in this order: a stop job, a user job, the
next poll transaction. A stop therefore waits at most for the one transaction in
flight (a few ms at 19200 baud), never for queued polls or commands.

The split: ``Slap2Wire`` (devices/slap2/exchange.py) does the exchange on the line; this
module owns what is known of each module (online, reset evidence, parameters, the
profile of its last move), the session loop, polling and capture scheduling.

The exchange follows the manual's host algorithm exactly ("sstring"/"rstring"): send
one character, wait for its echo and compare it, then the next; after the last one
send CR and wait for its echo; then collect the reply (chars > 31) up to CR. Decisions
where the manual is silent (also in docs/slap2.md):

* Echo mismatch or echo timeout before CR was sent: send Ctrl-X (the module discards
  its input buffer, so nothing executes), drain the line until it is quiet, and retry
  the command once. After CR a failure is not retried: the module may have executed
  it (``mr`` is not idempotent).
* Selection (``se n``) is cached. If no module is selected nobody echoes, so when
  the first character of ``se`` gets no echo the driver sends Ctrl-X and then the
  ``se`` line "blind", paced at two character times per character, and waits for the
  CR reply of the newly selected module. That is the only time a character is sent
  without waiting for the previous echo.
* Bytes that arrive while no transaction runs are unsolicited: late echoes of our
  own commands (a slow host let a timeout pass before they came), line noise, or a
  power-on banner. Only a line naming the module type (``SLAP2 ...``, what address 0
  sends after power-on) counts as a banner: that module was reset. Anything else is
  dropped and counted (``dropped_bytes``), never an alarm — the driver's own ``se0``
  or ``rss`` echo arriving late has letters too.
* Reset evidence must survive a slow host. Strong cues flag a reset at once: the
  banner, and a persisted parameter read back with another value than last read or
  written. Weak cues only make the module *suspect*: ``pm``/``vm`` dropping while the
  driver expects them, the ``cal`` flag falling (unless servotune started a
  calibration), and a module that answered only after a blind re-selection (one
  missed echo under load looks exactly like that). A suspect module is checked
  again at once after resynchronising: ``rss`` read again and every setting that
  differs from its default read back. Only if the check confirms (the mode is
  still lost, the flag still down, a setting changed) is the module flagged
  ``reset``; otherwise the cue is counted as a desync and forgotten.
* Ctrl-X is echoed like every byte. ``_abandon`` waits for that echo before it
  drains the line; an echo of Ctrl-X that comes even later is recognised where it
  lands (no command servotune sends contains 0x18: console lines with control
  characters are refused) and skipped, instead of being taken for the echo of the
  next command.
* Refusal: ``-1UC`` (syscon ``ucon`` set) or, when ``ucon`` is off, the ``uc`` bit of
  an ``rss`` read right after the command.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

from servotune.devices.slap2 import codec
from servotune.devices.slap2.axis import Slap2Axis
from servotune.devices.slap2.capture import (
    CAPTURE_UCON,
    CHECK_TOLERANCE_COUNTS,
    MISSES_TO_DROP,
    MOVE_MNEMONICS,
    PROFILE_BREAKERS,
    ModuleCapture,
    ProfileState,
)
from servotune.devices.slap2.descriptor import PARAM_SETTERS, slap2_descriptor
from servotune.devices.slap2.exchange import (
    ReplyTimeoutError,
    Slap2Wire,
    command_mnemonic,
    is_banner,
)
from servotune.devices.slap2.profile import TICK_S, ProfileTrack, firmware_setpoint
from servotune.link.base import (
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverError,
    DriverSink,
    InvalidArgumentError,
    ProtocolError,
    Sample,
    check_console_line,
)
from servotune.link.capture import CaptureRegistry, CaptureStats
from servotune.link.engine import recent_rate_hz
from servotune.link.setpoint import STEADY_ERROR_COUNTS, SkewedSetpoint
from servotune.schema import AxisHealth
from servotune.transports.base import ByteChannel, Connector

logger = logging.getLogger(__name__)

# Outside a capture pe is read one transaction after rp (~6 ms at 19200 baud): what the
# profile moves in that time is allowed in the live check of the reconstruction.
LIVE_SKEW_S = 0.01

T = TypeVar("T")

# Tries of switching syscon ucon for a capture (or back) before doing without.
UCON_ATTEMPTS = 3
# Polls of one module that fail in a row while the line's other modules answer between
# them: that module is taken offline and probed with a growing interval, as a module
# missing at start-up is. Polling it on would hold the line for its character timeouts
# on every cycle (the other modules fell from ~23 to ~1 sample/s) and show it as if it
# answered. Three, like the line's own rule: one or two failures are a slow host.
MODULE_OFFLINE_FAILURES = 3
# The line's rule: ``error`` after LINE_ERROR_FAILURES failed exchanges in a row. When
# bytes came back in that run (a wrong echo, an odd reply, a refusal, or a reply that
# did not come after the whole command was echoed: any failure but a silent line), the
# line is alive, and the run must also span LINE_ERROR_SPAN_S. (One missing reply is
# never an error: the next poll reads again - every poll is a read, safe to repeat.)
# Under a CPU hog one stall can hold a reply past the character timeout and its late
# bytes spoil the next two echoes: three failures within well under the span, then an
# answer; that is counted (desyncs, dropped bytes), not shown as an error. A dead line
# sends nothing back (timeouts only): the span does not apply to it, so its verdict is
# not delayed (figures in docs/architecture.md). Wrong baud or noise (only wrong
# bytes) shows after the span.
LINE_ERROR_FAILURES = 3
LINE_ERROR_SPAN_S = 0.9
REFUSAL_HINTS = {
    "ma": "a move needs position mode: switch on 'Position mode' (pm) first",
    "mr": "a move needs position mode: switch on 'Position mode' (pm) first",
    "pg": "pg is refused while position or velocity mode is on: Power off (st) first",
    "cal": "the module could not start the calibration",
    "ca": "the module could not start the calibration",
}


@dataclass(slots=True)
class Slap2LinkConfig:
    """Settings of one SLAP2 line. Times are deliberately below the manual's 200 ms."""

    link_id: str
    path: str
    addresses: list[int]
    baud: int = 19200
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


@dataclass(slots=True)
class _ModuleState:
    """What the owner task knows about one module; touched only by the owner task."""

    address: int
    online: bool = False
    position: int | None = None
    position_t: float | None = None
    following_error: int | None = None
    velocity: float | None = None
    rss: int | None = None
    rss_t: float | None = None  # when rss was read (latch time): the flags' read time
    cycles: int = 0
    hex_mode: bool = False
    ucon: bool = False
    expected_mode: str = "unknown"  # off | pm | vm | pwm | unknown
    known: dict[str, int] = field(default_factory=dict)
    verify_index: int = 0
    samples: deque[float] = field(default_factory=lambda: deque(maxlen=512))
    next_probe_t: float = 0.0
    probe_interval_s: float = 0.0
    # This module's exchanges (polls, verify reads, reset checks) that failed in a
    # row, and the line's answer count at the first of them (_module_failed).
    failures: int = 0
    answers_at_first_failure: int = 0
    silent_since_s: float | None = None  # taken offline for it (_module_silent) then
    # A weak reset cue waiting to be confirmed (see the module docstring), and whether
    # the cal flag was seen set since the last calibration servotune started.
    suspect: str = ""
    cal_seen: bool = False
    # Capture (devices/slap2/capture.py): the reconstructed profile of the last move
    # servotune sent, the state of a capture of this module, and whether it is paused
    # for another module's capture.
    profile: ProfileState = field(default_factory=ProfileState)
    # Outside a capture: rp + pe while pe is steady (drivers.setpoint), and how often
    # in a row it disagreed with the reconstructed profile (_live_setpoint).
    skewed: SkewedSetpoint = field(default_factory=SkewedSetpoint)
    live_misses: int = 0
    last_command_latch_s: float | None = None
    last_command_latch_span_s: float | None = None
    capture: ModuleCapture | None = None
    last_capture: CaptureStats | None = None
    paused: bool = False
    # servotune switched syscon ucon on for a capture and owes the rsb5 that restores
    # the module's own setting (slap2_capture.CAPTURE_UCON).
    ucon_restore: bool = False
    ucon_failures: int = 0


class Slap2Link(Slap2Wire):
    """Owner of one SLAP2 RS232 line; see the module docstring for the protocol rules."""

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
        super().__init__(
            config.link_id,
            config.path,
            config,
            connector,
            sink,
            clock=clock,
            reconnect_max_s=config.reconnect_max_s,
        )
        self.config = config
        self._descriptor = slap2_descriptor(config.lines)
        self._modules = {a: _ModuleState(a) for a in config.addresses}
        self._axes = [Slap2Axis(self, a) for a in config.addresses]
        self._poll_index = 0
        self._last_verify_t = 0.0
        self._consecutive_failures = 0
        # The current run of failed exchanges: when it began, and whether bytes came
        # back in it (see LINE_ERROR_SPAN_S).
        self._first_failure_t = 0.0
        self._failures_saw_bytes = False
        # Exchanges any module answered (polls, verify reads, checks, capture steps):
        # tells a silent module on a working line from a line that is down.
        self._answers = 0
        self._captures = CaptureRegistry(self._capture_changed)
        self._capture_index = 0

    def axis_id(self, address: int) -> str:
        return f"{self.config.link_id}-{address}"

    def axis_name(self, address: int) -> str:
        return self.config.names.get(address, f"SLAP2 #{address}")

    def module_state(self, address: int) -> _ModuleState:
        return self._modules[address]

    def _on_link_down(self) -> None:
        for module in self._modules.values():
            module.profile.clear()
            module.ucon_failures = 0
            module.failures = 0
            module.silent_since_s = None  # the line's outage says it now
            if module.online:
                module.online = False
                self._sink.on_axis_health(self.axis_id(module.address), "offline", "link down")

    # --- session ---------------------------------------------------------------------

    async def _session(self, channel: ByteChannel) -> None:
        self._forget_selection()
        self._set_state("connecting", f"draining power-on output on {self.path}")
        banner = await self._drain(channel, self.config.banner_quiet_s, self.config.banner_max_s)
        if banner.strip():
            text = codec.LineDecoder().feed(banner + b"\r")
            self._sink.on_event("info", None, f"{self.id}: power-on banner: {' | '.join(text)}")
        for module in self._modules.values():
            await self._probe(module)
        self._connected_once = True
        self._set_state("connected", self._connector.description)
        while True:
            job = self._take_job()
            if job is not None:
                await self._run_job(job)
                continue
            now = self._clock()
            online = [m for m in self._modules.values() if m.online]
            if not online:
                await self._wait_job_or(self.config.offline_retry_s)
                if not self.jobs_pending:
                    for module in self._modules.values():
                        await self._probe(module)
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
                    await self._confirm_suspect(suspect)
                    continue
                await self._capture_step(captured)
                continue
            suspect = next((m for m in online if m.suspect), None)
            if suspect is not None:
                await self._confirm_suspect(suspect)
                continue
            if now - self._last_verify_t >= self.config.verify_period_s:
                self._last_verify_t = now
                await self._verify_step(online)
                continue
            await self._poll_step(online)
            due = [m for m in self._modules.values() if not m.online and now >= m.next_probe_t]
            if due and not self.jobs_pending:
                # Retry absent modules with a growing interval: each try holds the line
                # for a few character timeouts, which must not starve the others or
                # delay a STOP more than once in a while.
                module = due[0]
                module.probe_interval_s = min(
                    max(module.probe_interval_s * 2, self.config.offline_retry_s), 30.0
                )
                module.next_probe_t = now + module.probe_interval_s
                await self._probe(module)

    async def _probe(self, module: _ModuleState) -> None:
        """Select a module and read all its parameters; marks it online or offline."""
        axis_id = self.axis_id(module.address)
        try:
            values = await self._read_params(module)
            rss = await self._read_int(module.address, "rss")
            rss_t = self._last_latch_t
        except DriverError as exc:
            if module.online or not self._connected_once:
                self._sink.on_event("warning", axis_id, f"module {module.address}: {exc}")
            module.online = False
            if module.silent_since_s is not None:
                # Taken offline by _module_silent: say for how long, and when next.
                now = self._clock()
                silent_s = now - module.silent_since_s
                # The loop set the next try before this probe; when every module is
                # offline the loop retries all of them every offline_retry_s instead.
                next_s = module.next_probe_t - now
                if next_s <= 0:
                    next_s = self.config.offline_retry_s
                message = (
                    f"module {module.address} offline for {silent_s:.0f} s, does not "
                    f"answer ({exc}); next try in {next_s:.0f} s"
                )
            else:
                message = str(exc)
            self._sink.on_axis_health(axis_id, "offline", message)
            return
        module.rss, module.rss_t = rss, rss_t
        flags = codec.decode_rss(rss)
        module.expected_mode = "pm" if flags["pm"] else "vm" if flags["vm"] else "off"
        module.cal_seen = flags["cal"]
        module.suspect = ""
        if module.silent_since_s is not None:
            silent_s = self._clock() - module.silent_since_s
            module.silent_since_s = None
            self._sink.on_event(
                "info", axis_id, f"module {module.address} answers again after {silent_s:.1f} s"
            )
        module.online = True
        module.probe_interval_s = 0.0
        self._sink.on_params(axis_id, values, "read")
        self._sink.on_axis_health(axis_id, *self._resumed_health(module))

    # --- unsolicited bytes and reset evidence (the wire's hooks) -----------------------

    def _note_unsolicited(self, data: bytes) -> None:
        text = " ".join(codec.LineDecoder().feed(data + b"\r")).strip()
        self._errors += 1
        if self._connected_once and is_banner(text):
            # Only address 0 sends a banner after power-on; all modules lose selection.
            self._forget_selection()
            message = f"power-on banner received ({text!r}): module reset"
            self._sink.on_event("warning", None, f"{self.id}: {message}")
            if 0 in self._modules:
                self._mark_reset(
                    self._modules[0], "module reset (power-on banner) — settings may be lost"
                )
        else:
            # Late echoes and noise: counted (shown with the link status), not alarmed.
            self._count("dropped_bytes", len(data))
            logger.info("%s: %d unsolicited byte(s) dropped: %r", self.id, len(data), data[:16])

    def _mark_reset(self, module: _ModuleState, message: str) -> None:
        module.expected_mode = "unknown"
        # syscon is back at its EEPROM value: assume ucon off (the safe side, rss after
        # every command); a capture reads it again before relying on it.
        module.ucon = False
        module.ucon_failures = 0
        module.suspect = ""
        module.profile.clear()
        self._sink.on_axis_health(self.axis_id(module.address), "reset", message)
        self._sink.on_event("warning", self.axis_id(module.address), message)

    def _lost_selection(self, address: int) -> None:
        if address in self._modules:
            self._suspect(self._modules[address], "it answered only after a blind re-selection")

    def _suspect(self, module: _ModuleState, cue: str) -> None:
        """A weak reset cue: check the module again before anyone is alarmed."""
        if not module.suspect:
            module.suspect = cue
            logger.info("%s: module %d suspect: %s", self.id, module.address, cue)

    async def _confirm_suspect(self, module: _ModuleState) -> None:
        """Look for reset evidence that a slow host cannot fake (module docstring)."""
        cue = module.suspect
        try:
            rss = await self._read_int(module.address, "rss")
            rss_t = self._last_latch_t
            evidence = self._rss_evidence(module, rss)
            if not evidence:
                evidence = await self._settings_evidence(module)
        except DriverError as exc:
            # Still no answer after resynchronising: the poll's own failure counting
            # takes it from here (offline after repeated silence); no reset flag.
            module.suspect = ""
            logger.info(
                "%s: module %d: check after %r failed: %s", self.id, module.address, cue, exc
            )
            self._module_failed(module, exc)  # counts the desync
            return
        self._module_answered(module)
        module.suspect = ""
        if evidence:
            self._mark_reset(
                module, f"{evidence} (after: {cue}): module reset? Settings may be lost"
            )
            module.expected_mode = "off"
        else:
            self._count("desyncs")
            logger.info("%s: module %d: %s, but no reset evidence", self.id, module.address, cue)
        module.rss, module.rss_t = rss, rss_t
        module.cal_seen = module.cal_seen and codec.decode_rss(rss)["cal"]

    def _rss_evidence(self, module: _ModuleState, rss: int) -> str:
        """What a freshly read ``rss`` says of a reset ("" if nothing)."""
        flags = codec.decode_rss(rss)
        if module.expected_mode in ("pm", "vm") and not flags["pm"] and not flags["vm"]:
            return f"the module left {module.expected_mode} without a stop"
        if module.cal_seen and not flags["cal"]:
            return "the cal flag fell without a new calibration"
        return ""

    async def _settings_evidence(self, module: _ModuleState) -> str:
        """Read back every known setting that differs from its default ("" if all match)."""
        for parameter in self._descriptor.parameters:
            expected = module.known.get(parameter.name)
            if expected is None or expected == parameter.default:
                continue
            value = await self._read_int(module.address, parameter.read_command)
            if value != expected:
                module.known[parameter.name] = value
                if parameter.name == "syscon":
                    self._learn_syscon(module, value)
                self._sink.on_params(self.axis_id(module.address), {parameter.name: value}, "read")
                return f"{parameter.name} reads {value}, last known {expected}"
        return ""

    # --- commands ---------------------------------------------------------------------

    async def _execute(self, module: _ModuleState, command: codec.Command) -> list[str]:
        """Run a state-changing command and raise DeviceRefusedError if refused."""
        mnemonic = command_mnemonic(command.text)
        previous: ProfileTrack | None = None
        resting = self._resting_setpoint(module)
        if mnemonic in MOVE_MNEMONICS or mnemonic in PROFILE_BREAKERS:
            # Whatever happens next, the old reconstruction no longer holds, except as
            # the start of a move replanned on top of it (kept aside for that).
            previous = module.profile.track
            module.profile.clear()
        lines = await self._transact(module.address, command)
        latched = module.last_command_latch_s = self._last_latch_t
        module.last_command_latch_span_s = self._last_latch_span_s
        reply = codec.parse_reply(lines[0] if lines else "")
        hint = REFUSAL_HINTS.get(mnemonic, "the module did not accept the command (uc)")
        if reply.kind is codec.ReplyKind.REFUSED:
            raise DeviceRefusedError(f"{command.text}: refused with -1UC: {hint}")
        if command.changes_device and not module.ucon:
            rss = await self._read_rss_after(command.text)
            module.rss, module.rss_t = rss, self._last_latch_t
            if codec.decode_rss(rss)["uc"]:
                raise DeviceRefusedError(f"{command.text}: refused (uc flag set): {hint}")
        if mnemonic in MOVE_MNEMONICS:
            self._start_profile(module, command.text, latched, previous, resting)
        return lines

    @staticmethod
    def _resting_setpoint(module: _ModuleState) -> float | None:
        """At rest in pm the setpoint is the held target: rp + pe of the last poll."""
        flags = codec.decode_rss(module.rss or 0)
        if (
            flags["pm"]
            and not flags["move"]
            and module.position is not None
            and module.following_error is not None
        ):
            return float(module.position + module.following_error)
        return None

    def _start_profile(
        self,
        module: _ModuleState,
        text: str,
        latched_s: float,
        previous: ProfileTrack | None,
        resting: float | None,
    ) -> None:
        """Reconstruct the profile of a move the module accepted (slap2_capture);
        ``resting``: the setpoint before it if the module was at rest in pm."""
        mnemonic = command_mnemonic(text)
        try:
            value = codec.parse_int(text[len(mnemonic) :])
        except codec.CodecError:
            return
        module.profile.track = previous
        module.profile.start(
            mnemonic,
            value,
            latched_s,
            module.known.get("velocity"),
            module.known.get("acceleration"),
            resting,
        )

    # --- parameters -------------------------------------------------------------------

    async def _read_params(self, module: _ModuleState) -> dict[str, int]:
        values: dict[str, int] = {}
        for parameter in self._descriptor.parameters:
            await self._let_stops_pass()
            values[parameter.name] = await self._read_int(module.address, parameter.read_command)
        self._learn_syscon(module, values.get("syscon"))
        module.known.update(values)
        return values

    def _learn_syscon(self, module: _ModuleState, syscon: int | None) -> None:
        if syscon is None:
            return
        bits = codec.decode_syscon(syscon)
        module.hex_mode = bits["hex"]
        module.ucon = bits["ucon"]

    async def _write_params(
        self, module: _ModuleState, values: Mapping[str, int]
    ) -> dict[str, int]:
        readback: dict[str, int] = {}
        for name, value in values.items():
            await self._let_stops_pass()
            parameter = self._descriptor.parameter(name)
            command = codec.make_set(command_mnemonic(parameter.set_command), value)
            try:
                await self._execute(module, command)
            except DeviceRefusedError as exc:
                raise DeviceRefusedError(f"{name}: {exc}") from exc
            readback[name] = await self._read_int(module.address, parameter.read_command)
            module.known[name] = readback[name]
            if name == "syscon":
                self._learn_syscon(module, readback[name])
                module.ucon_restore = False  # the user's setting now: nothing to restore
        return readback

    async def _verify_step(self, online: list[_ModuleState]) -> None:
        """Read back one persisted parameter of one module to catch silent resets."""
        module = online[self._poll_index % len(online)]
        # Values that differ from the defaults betray a reset first; check them only
        # while there are any.
        names = [
            p.name
            for p in self._descriptor.parameters
            if p.name in module.known and module.known[p.name] != p.default
        ] or [p.name for p in self._descriptor.parameters if p.name in module.known]
        if not names:
            return
        name = names[module.verify_index % len(names)]
        module.verify_index += 1
        parameter = self._descriptor.parameter(name)
        try:
            value = await self._read_int(module.address, parameter.read_command)
        except (DeviceTimeoutError, ProtocolError) as exc:
            self._module_failed(module, exc)
            return
        self._module_answered(module)
        expected = module.known[name]
        if value != expected:
            module.known[name] = value
            if name == "syscon":
                self._learn_syscon(module, value)
            default = parameter.default
            why = "back at its default" if value == default else "changed outside servotune"
            self._mark_reset(
                module,
                f"{name} reads {value}, last known {expected} ({why}): module reset? "
                "Settings may be lost",
            )
            self._sink.on_params(self.axis_id(module.address), {name: value}, "read")

    # --- polling ----------------------------------------------------------------------

    async def _poll_step(self, online: list[_ModuleState]) -> None:
        """Poll one module completely (rp, pe, rss; rve every n-th cycle)."""
        module = online[self._poll_index % len(online)]
        self._poll_index += 1
        try:
            await self._poll_module(module)
            self._module_answered(module)
        except DriverError as exc:
            self._module_failed(module, exc)

    def _module_answered(self, module: _ModuleState) -> None:
        """An exchange with ``module`` succeeded: the line works, and so does it."""
        if self._channel is not None:
            self._channel.take_timeout_late_s()  # timeouts before it excuse no later one
        self._device_answered()
        self._consecutive_failures = 0
        self._answers += 1
        module.failures = 0

    def _module_failed(self, module: _ModuleState, exc: DriverError) -> None:
        """Count a failed exchange with ``module`` (a poll, a verify read, a reset
        check) for the line's rule (``_poll_failed``) and for the module's own: it is
        taken offline after ``MODULE_OFFLINE_FAILURES`` in a row if
        another module answered since the first of them. Every kind counts: a
        silent module's verify read or reset check costs the line as much as its
        poll, and counting only polls let the hub's silence rule fire first. The
        line's answer count decides "another module answered" (this module's own
        answer would have reset its count), so a line that is down, or has one
        module, is left to the line's rule (_poll_failed): never shown connected
        with its only module offline. A timeout the host noticed later than it had
        listened (``_host_stalled``) counts for neither: the host was away."""
        if isinstance(exc, DeviceTimeoutError) and self._host_stalled(self.config.char_timeout_s):
            self._count("desyncs")
            return
        self._poll_failed(exc)
        if module.failures == 0:
            module.answers_at_first_failure = self._answers
        module.failures += 1
        if (
            module.failures >= MODULE_OFFLINE_FAILURES
            and self._answers > module.answers_at_first_failure
            and module.online
        ):
            self._module_silent(module, exc)

    def _module_silent(self, module: _ModuleState, exc: DriverError) -> None:
        """Take a module whose exchanges keep failing on a working line offline; the
        owner loop probes it again (``offline_retry_s``, doubling up to 30 s), and
        the probe that reads it brings it back."""
        axis_id = self.axis_id(module.address)
        failures = module.failures
        module.online = False
        module.failures = 0
        module.probe_interval_s = 0.0
        module.silent_since_s = self._clock()
        module.next_probe_t = module.silent_since_s + self.config.offline_retry_s
        message = (
            f"module {module.address} does not answer: {failures} exchanges in a row "
            f"failed while the line's other modules answered ({exc}); tried again with a "
            "growing interval"
        )
        self._sink.on_event("warning", axis_id, message)
        self._sink.on_axis_health(axis_id, "offline", message)

    def _poll_failed(self, exc: DriverError) -> None:
        # A failed exchange of the owner loop's own (a poll, a verify read, a reset
        # check): LINE_ERROR_FAILURES in a row with no answer between (spread over
        # LINE_ERROR_SPAN_S if bytes came back) and the line shows ``error``. An odd
        # reply to a poll is a desynchronisation, never the end of the session:
        # counted, the next poll resynchronises (select, echo check).
        self._count("desyncs")
        now = self._clock()
        if self._consecutive_failures == 0:
            self._first_failure_t = now
            self._failures_saw_bytes = False
        self._consecutive_failures += 1
        self._failures_saw_bytes |= isinstance(exc, ReplyTimeoutError) or not isinstance(
            exc, DeviceTimeoutError
        )
        if self._consecutive_failures >= LINE_ERROR_FAILURES and (
            not self._failures_saw_bytes or now - self._first_failure_t >= LINE_ERROR_SPAN_S
        ):
            if self._state != "error":
                self._sink.on_event("error", None, f"{self.id}: {exc}")
            self._set_state("error", str(exc))
            if self._consecutive_failures >= 3 * len(self._modules):
                for m in self._modules.values():
                    m.online = False
                    self._sink.on_axis_health(self.axis_id(m.address), "offline", str(exc))

    async def _poll_module(self, module: _ModuleState) -> None:
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
            if self.urgent_pending:
                # A stop is waiting: give the line up now, finish the sample later.
                return
            then = sequence[index + 1] if index + 1 < len(sequence) else None
            value = await self._read_int(address, mnemonic, then)
            if mnemonic == "rp":
                position, t_position = value, self._last_latch_t
            elif mnemonic == "pe":
                following_error = value
            elif mnemonic == "rss":
                rss, rss_t = value, self._last_latch_t
        measured: float | None = None
        module.cycles += 1
        if rve_due:
            measured = await self._read_int(address, "rve") * codec.COUNTS_S_PER_SV
        if self._state == "error":
            self._set_state("connected", self._connector.description)
        self._emit_sample(module, position, t_position, following_error, rss, rss_t, measured)

    def _emit_sample(
        self,
        module: _ModuleState,
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
            self._check_rss(module, rss)
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
        self, module: _ModuleState, flags: Mapping[str, bool], t: float, skewed: float | None
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
        self._count("setpoint_mismatches")
        logger.info(
            "%s: module %d: rp + pe %.0f, the reconstructed setpoint %.0f: dropped",
            self.id,
            module.address,
            skewed,
            reconstructed,
        )
        return None

    def _check_rss(self, module: _ModuleState, rss: int) -> None:
        cue = self._rss_evidence(module, rss)
        if cue:
            self._suspect(module, cue)
        elif codec.decode_rss(rss)["cal"]:
            module.cal_seen = True

    # --- capture (drivers.base.Capturer; decisions in devices/slap2/capture.py) ---------

    def capture(self, address: int, reason: str) -> contextlib.AbstractAsyncContextManager[None]:
        """Devote the line to module ``address`` while the context is open."""
        if address not in self._modules:
            raise InvalidArgumentError("address", f"no module {address} on {self.id}")
        return self._captures.hold(address, reason)

    def _resumed_health(self, module: _ModuleState) -> tuple[AxisHealth, str]:
        """The health of a module found online again: paused if another is captured."""
        if module.paused:
            on = ", ".join(f"#{a}" for a in sorted(self._captures.addresses))
            return "paused", f"paused: capture on {on}"
        return "ok", ""

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
        self._wakeup.set()

    async def _capture_step(self, captured: list[_ModuleState]) -> None:
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
        chars_before = self._wire_chars
        fresh_pe: int | None = None
        # The step's reads are planned before its rp, so that each can be chained from
        # the reply before it (see _exchange_once): pe and rss if due now, then the
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
            position = await self._read_int(address, "rp", "pe" if pe_due else after_pe)
            t, t_span = self._last_latch_t, self._last_latch_span_s
            why = capture.resolve(module.profile, t, position)
            if why:
                self._count("setpoint_mismatches")
                logger.info("%s: module %d: %s", self.id, address, why)
            flags = codec.decode_rss(module.rss or 0)
            if not self.urgent_pending and pe_due:
                fresh_pe = await self._read_int(address, "pe", after_pe)
                capture.pending = (self._last_latch_t, fresh_pe)
                capture.last_pe_s = self._last_latch_t
                capture.samples_since_pe = 0
                module.following_error = fresh_pe
                capture.note_rest(module.profile, flags, t, position + fresh_pe)
            else:
                capture.samples_since_pe += 1
            if not self.urgent_pending and rss_due:
                rss = await self._read_int(address, "rss", after_rss)
                capture.last_rss_s = self._last_latch_t
                self._check_rss(module, rss)
                module.rss, module.rss_t = rss, self._last_latch_t
            self._module_answered(module)
        except DriverError as exc:
            capture.stats.wire_chars += self._wire_chars - chars_before
            self._poll_failed(exc)
            return
        capture.stats.wire_chars += self._wire_chars - chars_before
        capture.stats.samples += 1
        capture.previous = (t, position)
        if self._state == "error":
            self._set_state("connected", self._connector.description)
        self._emit_captured(module, t, position, fresh_pe, t_span)

    async def _switch_ucon(self, module: _ModuleState, *, on: bool) -> None:
        """Switch syscon ``ucon`` on for a capture (``ssb5``) or restore it (``rsb5``).

        With ucon on a refused command answers ``-1UC``, so a move (an injection sends
        one every few samples) needs no ``rss`` after it. Switching on reads syscon
        first (after a reset the driver no longer knows it) and leaves a module that
        has ucon on by itself alone. Failures count like a failed poll; the owner loop
        tries again on its next turn.
        """
        bit = codec.SysconBit.ucon.value
        try:
            syscon = await self._read_int(module.address, "rsyscon")
            if codec.decode_syscon(syscon)["ucon"] != on:
                await self._execute(module, codec.make_set("ssb" if on else "rsb", bit))
                syscon = await self._read_int(module.address, "rsyscon")
                module.ucon_restore = on
        except DriverError as exc:
            self._poll_failed(exc)
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
        self._learn_syscon(module, syscon)
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
        module: _ModuleState,
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
            return 1 / ((2 * 3 + self._reply_chars.get("rp", 2)) * char_s * len(captures))
        online = [m for m in self._modules.values() if m.online] or list(self._modules.values())
        per_module = 0.0
        for mnemonic in self.config.poll_commands:
            reply = self._reply_chars.get(mnemonic, 2)
            per_module += 2 * (len(mnemonic) + 1) + reply
        if self.config.rve_every:
            per_module += (2 * 4 + self._reply_chars.get("rve", 2)) / self.config.rve_every
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
            return await self._read_params(module)

        values = await self.submit(job)
        self._sink.on_params(self.axis_id(address), values, "read")
        return values

    async def op_write_params(
        self, address: int, values: Mapping[str, int], source: str
    ) -> dict[str, int]:
        module = self._modules[address]

        async def job() -> dict[str, int]:
            return await self._write_params(module, values)

        readback = await self.submit(job)
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
                await self._execute(module, command)
                sent.append(command.text)
                self._track_mode(module, command.text)
            return sent

        is_stop = any(c.text == "st" for c in commands) if stop is None else stop
        return await self.submit(job, urgent=urgent, axis=address, motion=True, stop=is_stop)

    async def op_raw_byte(self, address: int, byte: int, *, urgent: bool = False) -> None:
        """Send one control character (Ctrl-K) to a module and drain its echo."""

        async def job() -> None:
            channel = self._require_channel()
            if await self._settle_chain(channel):
                self._selected = None
            await self._select(address)
            await channel.write(bytes([byte]))
            await self._drain(channel, self.config.quiet_s, 0.2)

        await self.submit(job, urgent=urgent)

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
            lines = await self._transact(address, command)
            if lines and codec.parse_reply(lines[0]).kind is codec.ReplyKind.REFUSED:
                raise DeviceRefusedError(f"{text}: refused by the module (-1UC)")
            if not module.ucon and mnemonic not in ("rss", "ss", "rrss"):
                # Without ucon a refusal is a bare CR: the uc flag tells (rss leaves it).
                rss = await self._read_rss_after(text)
                if codec.decode_rss(rss)["uc"]:
                    raise DeviceRefusedError(
                        f"{text}: refused by the module (uc flag set: unknown command, "
                        "bad argument, or not allowed in this mode)"
                    )
            self._track_mode(module, text)
            if mnemonic == "ssyscon" or mnemonic in ("ssb", "rsb"):
                module.known.pop("syscon", None)
                module.ucon_restore = False  # the user's setting now: nothing to restore
                self._learn_syscon(module, await self._read_int(address, "rsyscon"))
            return lines

        # A raw line may move the axis (vm, ma, spwm ...): a STOP discards it too.
        return text, await self.submit(job, axis=address, motion=True, stop=mnemonic == "st")

    def _track_mode(self, module: _ModuleState, text: str) -> None:
        mnemonic = command_mnemonic(text)
        if mnemonic in PROFILE_BREAKERS:
            module.profile.clear()
        if mnemonic == "st":
            module.expected_mode = "off"
        elif mnemonic in ("pm", "vm"):
            module.expected_mode = mnemonic
        elif mnemonic == "spwm":
            module.expected_mode = "pwm"
        elif mnemonic in ("cal", "ca"):
            module.expected_mode = "unknown"
            module.cal_seen = False  # a new calibration clears the flag until it ends
        elif mnemonic in PARAM_SETTERS:
            module.known.pop(PARAM_SETTERS[mnemonic], None)


__all__ = ["Slap2Axis", "Slap2Link", "Slap2LinkConfig", "is_banner"]
