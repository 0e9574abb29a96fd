"""The SLAP2 manual's host exchange on one RS232 line (the lower half of the driver).

``Slap2Exchange`` is the part of a SLAP2 link that talks to the line: the manual's
"sstring"/"rstring" (send a character, compare its echo, the next; CR; the reply up to
CR), module selection with ``se n`` (cached, and sent "blind" when nobody can echo),
Ctrl-X recovery before CR, the one retry a failure before CR allows, and the latch
time of every reply.

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
* Ctrl-X is echoed like every byte. ``abandon`` waits for that echo before it
  drains the line; an echo of Ctrl-X that comes even later is recognised where it
  lands (no command servotune sends contains 0x18: console lines with control
  characters are refused) and skipped, instead of being taken for the echo of the
  next command.

Seam: this class knows the line's selection and nothing else about the modules. The
link *has* one, beside its ``LinkEngine`` (whose channel, counters and job queues the
exchange uses), and hears what only it can judge through ``ExchangeEvents``:
``note_unsolicited`` (bytes that came outside any exchange: a banner means a reset) and
``lost_selection`` (the selected module answered only after a blind re-selection: a
weak reset cue).
"""

from __future__ import annotations

import asyncio
from typing import Protocol

from servotune.devices.slap2 import codec
from servotune.devices.slap2.echo import EchoLine, EchoResult
from servotune.link.base import DeviceTimeoutError, DriverError, ProtocolError
from servotune.link.engine import LinkEngine
from servotune.transports.base import ByteChannel

# Commands that may run twice with the same effect: sent again after a failure that
# came after their CR (for any other command that failure is final: it may have run).
IDEMPOTENT_COMMANDS = frozenset({"st"})
# Reads the poll loops chain (``exchange_once(then=...)``): sending one for nothing
# (the loop asked for something else after all) costs line time, never a change.
CHAINABLE_READS = frozenset({"rp", "pe", "rss", "rve"})
SLOW_COMMANDS_REPLY_S = {"pg": 1.0, "de": 1.0, "rep": 0.5, "rrss": 0.5, "rrsyscon": 0.5}


class WireTiming(Protocol):
    """The timing settings the exchange needs (``Slap2LinkConfig`` has them)."""

    @property
    def baud(self) -> int: ...
    @property
    def char_timeout_s(self) -> float: ...
    @property
    def quiet_s(self) -> float: ...
    @property
    def listing_quiet_s(self) -> float: ...


class ExchangeEvents(Protocol):
    """What the exchange reports that only the link can judge (the link implements it)."""

    def note_unsolicited(self, data: bytes) -> None:
        """Bytes that arrived outside any exchange (late echoes, noise, a banner)."""

    def lost_selection(self, address: int) -> None:
        """Module ``address`` was selected, yet answered only after a blind ``se``."""


class Slap2Exchange:
    """The SLAP2 exchange on the channel of ``engine``'s current session.

    Only the owner task calls these methods (``LinkEngine``'s rule). ``transact``
    selects and exchanges one command (retried once if abandoned before CR);
    ``exchange_once`` exchanges with the module already selected; ``read_int`` and
    ``read_rss_after`` parse a number. Errors: ``DeviceTimeoutError`` (no echo or no
    reply), ``ProtocolError`` (a wrong echo or reply), ``_AbandonedError`` (failed
    before CR: nothing executed). ``last_latch_t`` / ``last_latch_span_s``: when the
    module latched the last exchange's value and how far before that it may lie;
    ``wire_chars``: the characters all exchanges took on the wire.
    """

    def __init__(self, timing: WireTiming, engine: LinkEngine, events: ExchangeEvents) -> None:
        self._timing = timing
        self._engine = engine
        self._events = events
        self._clock = engine.clock
        # The echo operations on the current session's channel; the chained reads
        # it sent for nothing (see exchange_once) go to ``chained_reads_dropped``.
        self._line: EchoLine | None = None
        self._chain_drops_seen = 0
        engine.count("chained_reads_dropped", 0)
        self._selected: int | None = None
        # The last module we selected, kept when ``_selected`` is forgotten after an
        # error, to tell a reset (it lost its selection) from a glitch.
        self._believed_selected: int | None = None
        # The address of the last ``se`` that nobody answered: that module holds the
        # line's selection with its transmitter dark, so the next ``se`` cannot be
        # echoed and is sent blind at once (saves a character timeout and a Ctrl-X
        # recovery, about 0.35 s, per cycle while a module is silent).
        self._dark_selection: int | None = None
        # The reply length last seen per mnemonic (the link's wire limit counts them).
        self.reply_chars: dict[str, int] = {}
        # Best estimate of when the module latched the last exchange's value (see
        # ``exchange_once``), and the character times all exchanges took on the wire.
        self.last_latch_t = 0.0
        # ... and how far before it the latch may lie: down to when the CR was written
        # (None: not known, e.g. after the slow path of a stray echo).
        self.last_latch_span_s: float | None = None
        self.wire_chars = 0

    def forget_selection(self) -> None:
        """A new session or a reset: nobody is known to be selected."""
        self._selected = self._believed_selected = self._dark_selection = None

    def deselect(self) -> None:
        """An exchange failed so that the selection is in doubt: select again before the
        next command (the module believed selected is kept, to tell a reset later)."""
        self._selected = None

    async def drain(self, channel: ByteChannel, quiet_s: float, max_s: float) -> bytes:
        """Read until nothing arrives for ``quiet_s`` (or ``max_s`` passed)."""
        collected = bytearray(channel.discard_input())
        deadline = self._clock() + max_s
        while self._clock() < deadline:
            data = await channel.read_available(quiet_s)
            if not data:
                break
            collected += data
        return bytes(collected)

    async def abandon(self, channel: ByteChannel, head: bytes = b"") -> None:
        """Ctrl-X discards a half-sent command in the module; then wait for quiet.

        The module echoes the Ctrl-X: wait for that echo first (up to a character
        timeout), so it cannot arrive during the next command and pass for its echo.
        """
        await channel.write(bytes([codec.CTRL_X]))
        leftover = bytearray(head)
        deadline = self._clock() + self._timing.char_timeout_s
        while codec.CTRL_X not in leftover:
            remaining = deadline - self._clock()
            if remaining <= 0:
                break
            data = await channel.read_available(remaining)
            if not data:
                break
            leftover += data
        leftover += await self.drain(channel, self._timing.quiet_s, 0.5)
        stray = bytes(leftover).replace(bytes([codec.CTRL_X]), b"")
        if stray.strip(b"\r\n"):
            self._events.note_unsolicited(stray)

    async def _send_echoed(
        self, channel: ByteChannel, text: str, first: EchoResult | None = None
    ) -> None:
        """Send ``text`` + CR one char at a time, each after the previous echo.

        ``first``: the outcome of an echoed write of the whole line already made (by
        ``EchoLine.transact``) that stopped early; the rest is sent from there.
        Raises ``_AbandonedError`` for failures before CR was sent (the command was
        abandoned with Ctrl-X and did not execute, so it may be retried).
        """
        payload = text.encode("ascii") + b"\r"
        done = 0
        while True:
            if first is not None:
                result, first = first, None
            else:
                result = await self._line_of(channel).write_echoed(
                    payload[done:], self._timing.char_timeout_s
                )
            done += result.echoed
            if done == len(payload):
                return
            if result.got != codec.CTRL_X:
                break
            # A late echo of our own Ctrl-X (nothing else sends 0x18): skip it; the
            # echo of the byte just sent is due next.
            self._engine.count("desyncs")
            echo = await self._line_of(channel).read_byte(self._timing.char_timeout_s)
            if echo != payload[done]:
                result = EchoResult(result.echoed, echo)
                break
            done += 1
            if done == len(payload):
                return
        byte = payload[done]
        if result.got is None:
            error: DriverError = DeviceTimeoutError(
                f"no echo for {chr(byte)!r} of {text!r} (cable, power or address?)"
            )
        else:
            error = ProtocolError(
                f"echo mismatch in {text!r}: sent {byte:#04x}, got {result.got:#04x}"
            )
        if done == len(payload) - 1:  # CR was sent: it may have executed
            raise error
        # The wrong byte may be the head of a banner: keep it with what follows.
        await self.abandon(channel, b"" if result.got is None else bytes([result.got]))
        raise _AbandonedError(error)

    def _first_reply_timeout_s(self, command: codec.Command) -> float:
        return max(
            self._timing.char_timeout_s,
            SLOW_COMMANDS_REPLY_S.get(command_mnemonic(command.text), 0.0),
        )

    async def _read_reply(
        self, channel: ByteChannel, command: codec.Command, raw: bytes | None = None
    ) -> list[str]:
        """The reply's lines; ``raw``: its first line if already read (by ``transact``)."""
        decoder = codec.LineDecoder()
        if raw is None:
            raw = await self._line_of(channel).read_until(
                codec.CR, self._first_reply_timeout_s(command), self._timing.char_timeout_s
            )
        if raw is None:
            raise ReplyTimeoutError(f"no reply to {command.text!r}")
        lines = decoder.feed(raw)
        if command.multiline:
            # Listings are for terminals: read until the line goes quiet.
            listing = command_mnemonic(command.text) in codec.MULTILINE_COMMANDS
            quiet_s = self._timing.listing_quiet_s if listing else self._timing.quiet_s
            while True:
                data = await channel.read_available(quiet_s)
                if not data:
                    break
                lines.extend(decoder.feed(data))
            if decoder.pending:
                lines.append(decoder.flush())
        return lines

    async def exchange_once(
        self, command: codec.Command, then: codec.Command | None = None
    ) -> list[str]:
        """One exchange with the selected module; no retry.

        ``then``: the read (``CHAINABLE_READS``) the caller will most likely make
        next on the same selection. The channel starts it from the callback that
        completes this reply, unless a job (a STOP above all) is waiting by then:
        at 19200 baud that takes the host's wake-up and parsing time (~50-100 us per
        exchange on a loaded server) off the line. A later exchange that is not
        that read first waits for it to end (one read's time, ~6 ms).

        Raises ``_AbandonedError`` when it failed before CR (nothing executed),
        ``DeviceTimeoutError``/``ProtocolError`` when it failed after CR.
        """
        channel = self._engine.require_channel()
        payload = command.text.encode("ascii") + b"\r"
        await self.settle_chain(channel, payload)
        stray = channel.discard_input()
        if stray:
            self._events.note_unsolicited(stray)
        try:
            # The usual case in one channel call: the echo checked and the reply read
            # in the receive callback, both arrival times stamped there.
            chain = (
                then is not None
                and command_mnemonic(command.text) in CHAINABLE_READS
                and command_mnemonic(then.text) in CHAINABLE_READS
            )
            done = await self._line_of(channel).transact(
                payload,
                codec.CR,
                self._timing.char_timeout_s,
                self._first_reply_timeout_s(command),
                then=then.text.encode("ascii") + b"\r" if chain and then else b"",
                may_chain=self._may_chain,
            )
            t_echo, t_reply, t_sent = done.t_echo_s, done.t_reply_s, done.t_sent_s
            if done.echo.echoed < len(payload):
                # A stray or missing echo: resynchronise the slow way.
                await self._send_echoed(channel, command.text, done.echo)
                t_echo = self._clock()
                t_sent = None
                raw = None
            else:
                raw = done.reply
                if raw is None:
                    raise ReplyTimeoutError(f"no reply to {command.text!r}")
            lines = await self._read_reply(channel, command, raw)
            if t_reply is None or raw is None or command.multiline:
                t_reply = self._clock()
        except _AbandonedError:
            self._engine.add_error()
            raise
        except DeviceTimeoutError:
            self._engine.add_error()
            self._selected = None
            await self.abandon(channel)
            raise
        if (
            not command.multiline
            and command_mnemonic(command.text) != "id"
            and any(is_banner(x) for x in lines)
        ):
            # A module powered up while we waited for this reply: its banner came
            # instead (a reset). The reply, if any, is lost.
            self._events.note_unsolicited("\r".join(lines).encode("ascii", "replace"))
            raise ProtocolError(f"power-on banner instead of the reply to {command.text!r}")
        reply_chars = sum(len(x) + 1 for x in lines)
        self.reply_chars[command_mnemonic(command.text)] = reply_chars
        # When the module latched the value: it acts on the CR, whose echo ends one
        # character later, and (sent back to back) the reply ends reply_chars after
        # that. Both clock readings can only be late (a busy host resumes this task
        # late), so each gives an upper bound; the smaller one is the best estimate.
        # The time the reply was parsed would bias rise and settling times by the
        # reply length and by the host's load.
        char_s = 10 / self._timing.baud
        if t_echo is None:
            t_echo = t_reply
        self.last_latch_t = min(t_echo - char_s, t_reply - (reply_chars + 1) * char_s)
        # The module cannot have acted before the CR was written: a host that ran the
        # echo's callback late (a stall) stamps late by the stall, and this says so.
        self.last_latch_span_s = None if t_sent is None else max(0.0, self.last_latch_t - t_sent)
        chars = 2 * (len(command.text) + 1) + reply_chars
        self.wire_chars += chars
        self._engine.wire_used(chars * char_s)
        return lines

    async def select(self, address: int) -> None:
        if self._selected == address:
            return
        channel = self._engine.require_channel()
        believed = self._believed_selected
        dark = self._dark_selection
        command = codec.make_select(address)
        try:
            if dark is not None:
                # The last ``se`` reached every module and selected a silent one: no
                # echo can come, so straight to the blind form (once: not again on its
                # own timeout).
                lines, blind = await self._select_blind(channel, command), True
            else:
                try:
                    lines, blind = await self._select_echoed(channel, command)
                except ProtocolError as wrong:
                    # A wrong echo of ``se``: one garbled character on a loaded line, or
                    # two transmitters - module 0 powered up selected while another
                    # module held the selection, so every byte comes back twice (on a
                    # real line the two collide) and no echoed ``se`` can ever pass.
                    # Selecting has no effect but the selection, and ``se n`` leaves n
                    # alone transmitting whoever echoed it and whether the first ran,
                    # so it is sent once more, blind (counted): that works with one
                    # transmitter, two or none. Commands that move are never resent.
                    # (Not a lost-selection cue: the selected module did not go silent.)
                    self._engine.count("retries")
                    try:
                        lines, blind = await self._select_blind(channel, command), False
                    except DeviceTimeoutError:
                        # No CR after it either: a line that answers only wrong bytes
                        # (wrong baud rate, noise) - what it showed first says so.
                        raise wrong from None
        except BaseException as exc:
            # Every module saw ``se n``: whoever was selected switched its transmitter
            # off, for a known reason; its later silence is no sign of a reset.
            self._selected = self._believed_selected = None
            self._dark_selection = address if isinstance(exc, DeviceTimeoutError) else None
            raise
        if lines != [""]:
            raise ProtocolError(f"unexpected reply to {command.text!r}: {lines!r}")
        self._dark_selection = None
        self._selected = self._believed_selected = address
        # (After a dark selection nothing is believed selected, so no cue then.)
        if blind and believed is not None:
            # The module we had selected stopped transmitting without an ``se``: a
            # reset (power-on deselects every address but 0) does that, but so does
            # one echo lost or late on a slow host. Weak evidence: the link checks it.
            self._events.lost_selection(believed)

    async def _select_echoed(
        self, channel: ByteChannel, command: codec.Command
    ) -> tuple[list[str], bool]:
        """``se n`` the usual way; sent blind if it got no echo (perhaps nobody is
        selected, so nobody could echo). Returns (the reply's lines, sent blind)."""
        try:
            return await self.exchange_once(command), False
        except _AbandonedError as abandoned:
            if not isinstance(abandoned.error, DeviceTimeoutError):
                raise abandoned.error from None
        except DeviceTimeoutError:
            pass
        return await self._select_blind(channel, command), True

    async def _select_blind(self, channel: ByteChannel, command: codec.Command) -> list[str]:
        """Send ``se n`` paced, without waiting for echoes, and await the new module's
        CR: for when nobody may be able to echo (nobody selected, or the selected
        module is silent).

        Should the old module transmit after all, it echoes the line before it
        switches off: one such echo is removed before the CR is looked for, so it
        cannot pass for the new module's reply. Any other bytes (late echoes, noise)
        go to ``ExchangeEvents.note_unsolicited``; a power-on banner among them means the module
        reset and the ``se`` is lost, a ``ProtocolError``.
        """
        char_s = 10 / self._timing.baud
        await self.settle_chain(channel)
        stray = channel.discard_input()
        if stray:
            self._events.note_unsolicited(stray)
        payload = command.text.encode("ascii") + b"\r"
        for byte in payload:
            await channel.write(bytes([byte]))
            await asyncio.sleep(2 * char_s)
        received = await self.drain(channel, self._timing.char_timeout_s, 0.5)
        rest = received.replace(payload, b"", 1)
        if b"\r" not in rest:
            if rest.strip():
                self._events.note_unsolicited(rest)
            # The previous module echoed the line: the line is alive, only the new
            # module's CR is missing (late, or that module is absent).
            error = ReplyTimeoutError if received.strip() else DeviceTimeoutError
            raise error(
                f"no module answers at address {command.text[2:]} (power, cable, address pins?)"
            )
        other = rest.replace(b"\r", b"", 1)
        if other.strip(b"\r\n"):
            self._events.note_unsolicited(other)
            if is_banner(other.decode("ascii", "replace")):
                raise ProtocolError(f"power-on banner instead of the reply to {command.text!r}")
        return [""]

    async def settle_chain(self, channel: ByteChannel, adopt: bytes = b"") -> bool:
        """Before a new exchange: end a chained read that is not ``adopt`` (see
        ``exchange_once``). One that failed before its reply was complete (a wrong
        or missing echo, no reply) may have left part of its command in the module's
        buffer, which the next command would be glued to (``pe`` + ``st`` = ``pest``,
        refused: a STOP lost). So Ctrl-X and drain, as after any failed exchange.
        True when it failed so (the selection is then in doubt, like after a timeout).
        """
        line = self._line_of(channel)
        dropped = await line.settle(adopt)
        self._count_dropped_chains(line)
        if dropped is None or dropped.reply is not None:
            return False
        await self.abandon(channel)
        return True

    def _line_of(self, channel: ByteChannel) -> EchoLine:
        """The echo operations on ``channel`` (a new session's channel: a new line)."""
        line = self._line
        if line is None or line.channel is not channel:
            line = self._line = EchoLine(channel)
            self._chain_drops_seen = 0
        return line

    def _count_dropped_chains(self, line: EchoLine) -> None:
        if line.chains_dropped != self._chain_drops_seen:
            self._engine.count(
                "chained_reads_dropped", line.chains_dropped - self._chain_drops_seen
            )
            self._chain_drops_seen = line.chains_dropped

    def _may_chain(self) -> bool:
        """Called from the receive callback: no job waits for the line."""
        return not self._engine.jobs_pending

    async def transact(
        self, address: int, command: codec.Command, then: codec.Command | None = None
    ) -> list[str]:
        """Select ``address`` and exchange ``command``; retried once if abandoned.

        A retry re-selects first: a missing echo may mean the module lost its
        selection (reset), a wrong one a second transmitter (module 0 reset while
        another module was selected), which a plain resend could not fix. ``then``: see
        ``exchange_once`` (not on a retry).
        """
        idempotent = command_mnemonic(command.text) in IDEMPOTENT_COMMANDS
        channel = self._engine.require_channel()
        if await self.settle_chain(channel, command.text.encode("ascii") + b"\r"):
            self._selected = None  # a read failed: select again, as after a timeout
        for attempt in range(2):
            if attempt:
                self._engine.count("retries")
            await self.select(address)
            try:
                return await self.exchange_once(command, None if attempt else then)
            except _AbandonedError as abandoned:
                # A missing echo may be a lost selection (a reset), a wrong one a second
                # transmitter (module 0 reset while this one was selected): only an
                # ``se`` ends either, so the retry selects again.
                self._selected = None
                if attempt == 1:
                    raise abandoned.error from None
            except (DeviceTimeoutError, ProtocolError):
                # After CR: it may have run. Only a command that may run twice (st)
                # is sent again - a STOP whose CR echo came late must still go out.
                if not idempotent or attempt == 1:
                    raise
        raise AssertionError("unreachable")

    async def read_rss_after(self, command_text: str) -> int:
        """``rss`` right after a command, on the same selection.

        Its ``uc`` bit tells whether the command was refused; a re-selection would
        spoil that (``se`` is a command too), so a failed read is repeated without
        one. If it still fails, the outcome is unknown and the error says so.
        """
        for attempt in range(3):
            try:
                lines = await self.exchange_once(codec.make_read("rss"))
            except _AbandonedError as abandoned:
                if attempt < 2:
                    self._engine.count("retries")
                    continue
                error = abandoned.error
            except (DeviceTimeoutError, ProtocolError) as exc:
                error = exc
            else:
                reply = codec.parse_reply(lines[0] if lines else "")
                if reply.kind is codec.ReplyKind.NUMBER and reply.value is not None:
                    return reply.value
                error = ProtocolError(f"rss answered {reply.text!r}, expected a number")
            raise ProtocolError(
                f"{command_text}: sent, but whether the module accepted it is unknown "
                f"(the status read after it failed: {error})"
            )
        raise AssertionError("unreachable")

    async def read_int(self, address: int, mnemonic: str, then: str | None = None) -> int:
        """``mnemonic``'s number; ``then``: the read most likely next (see
        ``exchange_once``)."""
        lines = await self.transact(
            address, codec.make_read(mnemonic), None if then is None else codec.make_read(then)
        )
        reply = codec.parse_reply(lines[0] if lines else "")
        if reply.kind is not codec.ReplyKind.NUMBER or reply.value is None:
            raise ProtocolError(f"{mnemonic} answered {reply.text!r}, expected a number")
        return reply.value


class ReplyTimeoutError(DeviceTimeoutError):
    """The line answered but the reply did not come in time: every character of the
    command was echoed, CR included (or, for a blind ``se``, the previous module echoed
    the line) and the reply (the new module's CR) is missing. A late reply, not a dead
    line: the link's error rule treats it like any failure that brought bytes back."""


class _AbandonedError(Exception):
    """A command abandoned with Ctrl-X before its CR: it did not execute."""

    def __init__(self, error: DriverError) -> None:
        super().__init__(str(error))
        self.error = error


def is_banner(text: str) -> bool:
    """A power-on banner names the module type (``SLAP2 V2205 HW3 SN10000``); late
    echoes of servotune's own commands (``se0``, ``rss``) and noise never do."""
    return "slap2" in text.lower()


def command_mnemonic(text: str) -> str:
    """The command word of a wire line: its leading letters (``sv1000`` -> ``sv``)."""
    end = 0
    while end < len(text) and text[end].isalpha():
        end += 1
    return text[:end].lower()


__all__ = [
    "IDEMPOTENT_COMMANDS",
    "ExchangeEvents",
    "ReplyTimeoutError",
    "Slap2Exchange",
    "WireTiming",
    "command_mnemonic",
    "is_banner",
]
