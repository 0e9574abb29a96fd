"""What a SLAP2 link knows of each module on its line, and the rules that change it.

``ModuleBook`` holds one ``ModuleState`` per address and decides, from the exchanges the
link's owner task makes, whether a module is online, silent, suspect or reset; it reads
and verifies the modules' parameters. Only the owner task calls it. The link
(``devices/slap2/link.py``) owns the session loop, polling, capture and commands, and
calls the book after each exchange; the book reads through the link's
``Slap2Exchange`` and reports through the hub's ``DriverSink``.

Rules (also in docs/slap2.md):

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
* A module whose exchanges keep failing while the line's other modules answer is
  taken offline and probed again with a growing interval (``MODULE_OFFLINE_FAILURES``);
  the line shows ``error`` after ``LINE_ERROR_FAILURES`` failed exchanges in a row
  (``LINE_ERROR_SPAN_S``).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

from servotune.descriptor import DeviceDescriptor
from servotune.devices.slap2 import codec
from servotune.devices.slap2.capture import (
    MOVE_MNEMONICS,
    PROFILE_BREAKERS,
    ModuleCapture,
    ProfileState,
)
from servotune.devices.slap2.descriptor import PARAM_SETTERS
from servotune.devices.slap2.exchange import (
    ReplyTimeoutError,
    Slap2Exchange,
    command_mnemonic,
    is_banner,
)
from servotune.devices.slap2.profile import ProfileTrack
from servotune.link.base import (
    DeviceRefusedError,
    DeviceTimeoutError,
    DriverError,
    DriverSink,
    ProtocolError,
)
from servotune.link.capture import CaptureRegistry, CaptureStats
from servotune.link.engine import LinkEngine
from servotune.link.setpoint import SkewedSetpoint
from servotune.schema import AxisHealth

logger = logging.getLogger(__name__)

REFUSAL_HINTS = {
    "ma": "a move needs position mode: switch on 'Position mode' (pm) first",
    "mr": "a move needs position mode: switch on 'Position mode' (pm) first",
    "pg": "pg is refused while position or velocity mode is on: Power off (st) first",
    "cal": "the module could not start the calibration",
    "ca": "the module could not start the calibration",
}

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


@dataclass(slots=True)
class ModuleState:
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
    # row, and the line's answer count at the first of them (``ModuleBook.failed``).
    failures: int = 0
    answers_at_first_failure: int = 0
    silent_since_s: float | None = None  # taken offline for it (``ModuleBook.failed``) then
    # A weak reset cue waiting to be confirmed (see the module docstring), and whether
    # the cal flag was seen set since the last calibration servotune started.
    suspect: str = ""
    cal_seen: bool = False
    # Capture (devices/slap2/capture.py): the reconstructed profile of the last move
    # servotune sent, the state of a capture of this module, and whether it is paused
    # for another module's capture.
    profile: ProfileState = field(default_factory=ProfileState)
    # Outside a capture: rp + pe while pe is steady (link.setpoint), and how often
    # in a row it disagreed with the reconstructed profile (the link's live check).
    skewed: SkewedSetpoint = field(default_factory=SkewedSetpoint)
    live_misses: int = 0
    last_command_latch_s: float | None = None
    last_command_latch_span_s: float | None = None
    capture: ModuleCapture | None = None
    last_capture: CaptureStats | None = None
    paused: bool = False
    # servotune switched syscon ucon on for a capture and owes the rsb5 that restores
    # the module's own setting (capture.CAPTURE_UCON).
    ucon_restore: bool = False
    ucon_failures: int = 0


class ModuleBook:
    """The modules of one SLAP2 line (``modules``: address -> ``ModuleState``) and the
    rules of the module docstring. Owner task only."""

    def __init__(
        self,
        addresses: list[int],
        engine: LinkEngine,
        exchange: Slap2Exchange,
        descriptor: DeviceDescriptor,
        captures: CaptureRegistry,
        *,
        char_timeout_s: float,
        offline_retry_s: float,
    ) -> None:
        self.modules = {a: ModuleState(a) for a in addresses}
        self._engine = engine
        self._exchange = exchange
        self._descriptor = descriptor
        self._captures = captures
        self._sink: DriverSink = engine.sink
        self._clock = engine.clock
        self._char_timeout_s = char_timeout_s
        self._offline_retry_s = offline_retry_s
        self._consecutive_failures = 0
        # The current run of failed exchanges: when it began, and whether bytes came
        # back in it (see LINE_ERROR_SPAN_S).
        self._first_failure_t = 0.0
        self._failures_saw_bytes = False
        # Exchanges any module answered (polls, verify reads, checks, capture steps):
        # tells a silent module on a working line from a line that is down.
        self._answers = 0

    def axis_id(self, address: int) -> str:
        return f"{self._engine.id}-{address}"

    def link_down(self) -> None:
        for module in self.modules.values():
            module.profile.clear()
            module.ucon_failures = 0
            module.failures = 0
            module.silent_since_s = None  # the line's outage says it now
            if module.online:
                module.online = False
                self._sink.on_axis_health(self.axis_id(module.address), "offline", "link down")

    # --- probe ------------------------------------------------------------------------

    async def probe(self, module: ModuleState) -> None:
        """Select a module and read all its parameters; marks it online or offline."""
        axis_id = self.axis_id(module.address)
        try:
            values = await self.read_params(module)
            rss = await self._exchange.read_int(module.address, "rss")
            rss_t = self._exchange.last_latch_t
        except DriverError as exc:
            if module.online or not self._engine.connected_once:
                self._sink.on_event("warning", axis_id, f"module {module.address}: {exc}")
            module.online = False
            if module.silent_since_s is not None:
                # Taken offline by _silent: say for how long, and when next.
                now = self._clock()
                silent_s = now - module.silent_since_s
                # The loop set the next try before this probe; when every module is
                # offline the loop retries all of them every offline_retry_s instead.
                next_s = module.next_probe_t - now
                if next_s <= 0:
                    next_s = self._offline_retry_s
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
        self._sink.on_axis_health(axis_id, *self.resumed_health(module))

    # --- unsolicited bytes and reset evidence -----------------------------------------

    def note_unsolicited(self, data: bytes) -> None:
        text = " ".join(codec.LineDecoder().feed(data + b"\r")).strip()
        self._engine.add_error()
        if self._engine.connected_once and is_banner(text):
            # Only address 0 sends a banner after power-on; all modules lose selection.
            self._exchange.forget_selection()
            message = f"power-on banner received ({text!r}): module reset"
            self._sink.on_event("warning", None, f"{self._engine.id}: {message}")
            if 0 in self.modules:
                self.mark_reset(
                    self.modules[0], "module reset (power-on banner) — settings may be lost"
                )
        else:
            # Late echoes and noise: counted (shown with the link status), not alarmed.
            self._engine.count("dropped_bytes", len(data))
            logger.info(
                "%s: %d unsolicited byte(s) dropped: %r", self._engine.id, len(data), data[:16]
            )

    def mark_reset(self, module: ModuleState, message: str) -> None:
        module.expected_mode = "unknown"
        # syscon is back at its EEPROM value: assume ucon off (the safe side, rss after
        # every command); a capture reads it again before relying on it.
        module.ucon = False
        module.ucon_failures = 0
        module.suspect = ""
        module.profile.clear()
        self._sink.on_axis_health(self.axis_id(module.address), "reset", message)
        self._sink.on_event("warning", self.axis_id(module.address), message)

    def lost_selection(self, address: int) -> None:
        if address in self.modules:
            self.suspect(self.modules[address], "it answered only after a blind re-selection")

    def suspect(self, module: ModuleState, cue: str) -> None:
        """A weak reset cue: check the module again before anyone is alarmed."""
        if not module.suspect:
            module.suspect = cue
            logger.info("%s: module %d suspect: %s", self._engine.id, module.address, cue)

    async def confirm_suspect(self, module: ModuleState) -> None:
        """Look for reset evidence that a slow host cannot fake (module docstring)."""
        cue = module.suspect
        try:
            rss = await self._exchange.read_int(module.address, "rss")
            rss_t = self._exchange.last_latch_t
            evidence = self.rss_evidence(module, rss)
            if not evidence:
                evidence = await self.settings_evidence(module)
        except DriverError as exc:
            # Still no answer after resynchronising: the poll's own failure counting
            # takes it from here (offline after repeated silence); no reset flag.
            module.suspect = ""
            logger.info(
                "%s: module %d: check after %r failed: %s",
                self._engine.id,
                module.address,
                cue,
                exc,
            )
            self.failed(module, exc)  # counts the desync
            return
        self.answered(module)
        module.suspect = ""
        if evidence:
            self.mark_reset(
                module, f"{evidence} (after: {cue}): module reset? Settings may be lost"
            )
            module.expected_mode = "off"
        else:
            self._engine.count("desyncs")
            logger.info(
                "%s: module %d: %s, but no reset evidence", self._engine.id, module.address, cue
            )
        module.rss, module.rss_t = rss, rss_t
        module.cal_seen = module.cal_seen and codec.decode_rss(rss)["cal"]

    def rss_evidence(self, module: ModuleState, rss: int) -> str:
        """What a freshly read ``rss`` says of a reset ("" if nothing)."""
        flags = codec.decode_rss(rss)
        if module.expected_mode in ("pm", "vm") and not flags["pm"] and not flags["vm"]:
            return f"the module left {module.expected_mode} without a stop"
        if module.cal_seen and not flags["cal"]:
            return "the cal flag fell without a new calibration"
        return ""

    async def settings_evidence(self, module: ModuleState) -> str:
        """Read back every known setting that differs from its default ("" if all match)."""
        for parameter in self._descriptor.parameters:
            expected = module.known.get(parameter.name)
            if expected is None or expected == parameter.default:
                continue
            value = await self._exchange.read_int(module.address, parameter.read_command)
            if value != expected:
                module.known[parameter.name] = value
                if parameter.name == "syscon":
                    self.learn_syscon(module, value)
                self._sink.on_params(self.axis_id(module.address), {parameter.name: value}, "read")
                return f"{parameter.name} reads {value}, last known {expected}"
        return ""

    def check_rss(self, module: ModuleState, rss: int) -> None:
        cue = self.rss_evidence(module, rss)
        if cue:
            self.suspect(module, cue)
        elif codec.decode_rss(rss)["cal"]:
            module.cal_seen = True

    # --- parameters and mode ----------------------------------------------------------

    async def read_params(self, module: ModuleState) -> dict[str, int]:
        values: dict[str, int] = {}
        for parameter in self._descriptor.parameters:
            await self._engine.let_stops_pass()
            values[parameter.name] = await self._exchange.read_int(
                module.address, parameter.read_command
            )
        self.learn_syscon(module, values.get("syscon"))
        module.known.update(values)
        return values

    def learn_syscon(self, module: ModuleState, syscon: int | None) -> None:
        if syscon is None:
            return
        bits = codec.decode_syscon(syscon)
        module.hex_mode = bits["hex"]
        module.ucon = bits["ucon"]

    async def verify(self, module: ModuleState) -> None:
        """Read back one persisted parameter of ``module`` to catch silent resets."""
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
            value = await self._exchange.read_int(module.address, parameter.read_command)
        except (DeviceTimeoutError, ProtocolError) as exc:
            self.failed(module, exc)
            return
        self.answered(module)
        expected = module.known[name]
        if value != expected:
            module.known[name] = value
            if name == "syscon":
                self.learn_syscon(module, value)
            default = parameter.default
            why = "back at its default" if value == default else "changed outside servotune"
            self.mark_reset(
                module,
                f"{name} reads {value}, last known {expected} ({why}): module reset? "
                "Settings may be lost",
            )
            self._sink.on_params(self.axis_id(module.address), {name: value}, "read")

    def track_mode(self, module: ModuleState, text: str) -> None:
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

    # --- failures: the module's rule and the line's -----------------------------------

    def answered(self, module: ModuleState) -> None:
        """An exchange with ``module`` succeeded: the line works, and so does it."""
        channel = self._engine.channel
        if channel is not None:
            channel.take_timeout_late_s()  # timeouts before it excuse no later one
        self._engine.device_answered()
        self._consecutive_failures = 0
        self._answers += 1
        module.failures = 0

    def failed(self, module: ModuleState, exc: DriverError) -> None:
        """Count a failed exchange with ``module`` (a poll, a verify read, a reset
        check) for the line's rule (``line_failed``) and for the module's own: it is
        taken offline after ``MODULE_OFFLINE_FAILURES`` in a row if
        another module answered since the first of them. Every kind counts: a
        silent module's verify read or reset check costs the line as much as its
        poll, and counting only polls let the hub's silence rule fire first. The
        line's answer count decides "another module answered" (this module's own
        answer would have reset its count), so a line that is down, or has one
        module, is left to the line's rule (``line_failed``): never shown connected
        with its only module offline. A timeout the host noticed later than it had
        listened (``LinkEngine.host_stalled``) counts for neither: the host was away."""
        if isinstance(exc, DeviceTimeoutError) and self._engine.host_stalled(self._char_timeout_s):
            self._engine.count("desyncs")
            return
        self.line_failed(exc)
        if module.failures == 0:
            module.answers_at_first_failure = self._answers
        module.failures += 1
        if (
            module.failures >= MODULE_OFFLINE_FAILURES
            and self._answers > module.answers_at_first_failure
            and module.online
        ):
            self._silent(module, exc)

    def _silent(self, module: ModuleState, exc: DriverError) -> None:
        """Take a module whose exchanges keep failing on a working line offline; the
        owner loop probes it again (``offline_retry_s``, doubling up to 30 s), and
        the probe that reads it brings it back."""
        axis_id = self.axis_id(module.address)
        failures = module.failures
        module.online = False
        module.failures = 0
        module.probe_interval_s = 0.0
        module.silent_since_s = self._clock()
        module.next_probe_t = module.silent_since_s + self._offline_retry_s
        message = (
            f"module {module.address} does not answer: {failures} exchanges in a row "
            f"failed while the line's other modules answered ({exc}); tried again with a "
            "growing interval"
        )
        self._sink.on_event("warning", axis_id, message)
        self._sink.on_axis_health(axis_id, "offline", message)

    def line_failed(self, exc: DriverError) -> None:
        # A failed exchange of the owner loop's own (a poll, a verify read, a reset
        # check): LINE_ERROR_FAILURES in a row with no answer between (spread over
        # LINE_ERROR_SPAN_S if bytes came back) and the line shows ``error``. An odd
        # reply to a poll is a desynchronisation, never the end of the session:
        # counted, the next poll resynchronises (select, echo check).
        self._engine.count("desyncs")
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
            if self._engine.state != "error":
                self._sink.on_event("error", None, f"{self._engine.id}: {exc}")
            self._engine.set_state("error", str(exc))
            if self._consecutive_failures >= 3 * len(self.modules):
                for m in self.modules.values():
                    m.online = False
                    self._sink.on_axis_health(self.axis_id(m.address), "offline", str(exc))

    def resumed_health(self, module: ModuleState) -> tuple[AxisHealth, str]:
        """The health of a module found online again: paused if another is captured."""
        if module.paused:
            on = ", ".join(f"#{a}" for a in sorted(self._captures.addresses))
            return "paused", f"paused: capture on {on}"
        return "ok", ""

    # --- commands ---------------------------------------------------------------------

    async def execute(self, module: ModuleState, command: codec.Command) -> list[str]:
        """Run a state-changing command and raise DeviceRefusedError if refused."""
        mnemonic = command_mnemonic(command.text)
        previous: ProfileTrack | None = None
        resting = self._resting_setpoint(module)
        if mnemonic in MOVE_MNEMONICS or mnemonic in PROFILE_BREAKERS:
            # Whatever happens next, the old reconstruction no longer holds, except as
            # the start of a move replanned on top of it (kept aside for that).
            previous = module.profile.track
            module.profile.clear()
        lines = await self._exchange.transact(module.address, command)
        latched = module.last_command_latch_s = self._exchange.last_latch_t
        module.last_command_latch_span_s = self._exchange.last_latch_span_s
        reply = codec.parse_reply(lines[0] if lines else "")
        hint = REFUSAL_HINTS.get(mnemonic, "the module did not accept the command (uc)")
        if reply.kind is codec.ReplyKind.REFUSED:
            raise DeviceRefusedError(f"{command.text}: refused with -1UC: {hint}")
        if command.changes_device and not module.ucon:
            rss = await self._exchange.read_rss_after(command.text)
            module.rss, module.rss_t = rss, self._exchange.last_latch_t
            if codec.decode_rss(rss)["uc"]:
                raise DeviceRefusedError(f"{command.text}: refused (uc flag set): {hint}")
        if mnemonic in MOVE_MNEMONICS:
            self._start_profile(module, command.text, latched, previous, resting)
        return lines

    @staticmethod
    def _resting_setpoint(module: ModuleState) -> float | None:
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
        module: ModuleState,
        text: str,
        latched_s: float,
        previous: ProfileTrack | None,
        resting: float | None,
    ) -> None:
        """Reconstruct the profile of a move the module accepted (devices/slap2/capture.py);
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

    async def write_params(self, module: ModuleState, values: Mapping[str, int]) -> dict[str, int]:
        readback: dict[str, int] = {}
        for name, value in values.items():
            await self._engine.let_stops_pass()
            parameter = self._descriptor.parameter(name)
            command = codec.make_set(command_mnemonic(parameter.set_command), value)
            try:
                await self.execute(module, command)
            except DeviceRefusedError as exc:
                raise DeviceRefusedError(f"{name}: {exc}") from exc
            readback[name] = await self._exchange.read_int(module.address, parameter.read_command)
            module.known[name] = readback[name]
            if name == "syscon":
                self.learn_syscon(module, readback[name])
                module.ucon_restore = False  # the user's setting now: nothing to restore
        return readback
