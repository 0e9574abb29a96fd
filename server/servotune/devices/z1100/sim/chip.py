"""Z1100 firmware emulation: three servo axes behind one serial line (sans-IO).

:class:`Z1100Chip` implements ``servotune.sim.base.SimDevice``: ``receive(byte)``
feeds one host byte and returns the reply when a packet completes; ``advance_to(t_s)``
runs the servo loops and the motors up to simulation time ``t_s`` and returns bytes the
chip sends by itself (the 100 ms packet-timeout reply, an injected noise reply). No
clock, no sockets, no randomness: the same calls give the same bytes.

The seam: this module is the chip *around* the axes - packet framing and its
timeout, the command interpreter (Get/Set, the "forbidden while moving" refusals,
Start/Stop/Zero), the flash file, resets and fault injections. One axis's servo law,
profiles and motor live in ``servotune.devices.z1100.sim.servo`` (the module docstring there
has the law); the servo knows nothing of the chip.

Decisions where the spec is silent are listed in docs/z1100-simulator.md and repeated
next to the code that implements them.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final

from servotune.devices.z1100.codec import (
    AXES,
    BAUD_RATES,
    CAB_MASK,
    COMMANDS,
    DEFAULT_BAUD,
    INT16_MAX,
    INT16_MIN,
    LIMIT_MAX_COUNTS,
    PACKET_TIMEOUT_S,
    STM_TICK_S,
    BadRequest,
    Command,
    Job,
    Reply,
    ReplyCode,
    Request,
    RequestDecoder,
    StartStatus,
    StopStatus,
    encode_reply,
    moving_flag,
    pack_error,
    pack_int32,
    pack_kab,
    pack_start,
    pack_stop,
    unpack_axes,
    unpack_int32,
    unpack_kab,
    unpack_start,
)
from servotune.devices.z1100.sim.servo import (
    _H_LEAVE,
    _H_SEEK,
    _HOME,
    _MOVE,
    _VELOCITY,
    AxisHardware,
    AxisParameters,
    AxisState,
    _Axis,
    _positive,
)
from servotune.sim.physics import DcMotor

# A "jammed" shaft (seized mechanism): Coulomb friction far beyond any stall torque.
_JAM_FRICTION_NM: Final = 100.0

FLASH_FORMAT: Final = "servotune-z1100-flash"
FLASH_VERSION: Final = 1

_TICKS_EPS: Final = 1e-9


@dataclass
class _Flash:
    """Where SetFlash writes: a JSON file, or memory when no path is given."""

    path: Path | None
    memory: list[dict[str, Any]] | None = field(default=None)

    def load(self) -> list[AxisParameters] | None:
        """The saved parameters, or ``None`` for a blank (or unreadable) flash."""
        document: object
        if self.path is None:
            document = {"axes": self.memory} if self.memory is not None else None
        else:
            try:
                document = json.loads(self.path.read_text(encoding="utf-8"))
            except FileNotFoundError:
                return None
            except (OSError, ValueError):
                return None  # unreadable or corrupt: like a blank flash
        if not isinstance(document, dict):
            return None
        axes = document.get("axes")
        if not isinstance(axes, list) or len(axes) != AXES:
            return None
        try:
            return [AxisParameters.from_json(entry) for entry in axes]
        except ValueError:
            return None

    def save(self, parameters: Sequence[AxisParameters]) -> None:
        """Write all axes' parameters (atomically for a file)."""
        entries = [p.to_json() for p in parameters]
        if self.path is None:
            self.memory = entries
            return
        document = {"format": FLASH_FORMAT, "version": FLASH_VERSION, "axes": entries}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        temporary = self.path.with_name(self.path.name + ".tmp")
        temporary.write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
        os.replace(temporary, self.path)  # never leave a half-written flash page


class Z1100Chip:
    """A simulated Z1100 with three motors; implements ``SimDevice`` and
    ``PowerCyclable``.

    Contract:

    * ``receive(byte)`` takes one host byte at the current simulation time (the last
      ``advance_to``) and returns the 6-byte reply when a packet completes, else
      ``b""``. Bytes other than 0x5A between packets are ignored.
    * ``advance_to(t_s)`` runs every axis's samples due up to ``t_s`` and returns what
      the chip sends by itself meanwhile: the bit-2 reply when a packet stayed
      incomplete for 100 ms, and replies queued by :meth:`inject_noise_reply`. The
      timeout reply is produced at the first ``advance_to``/``receive`` at or after
      the deadline, so its timing is as fine as the carrier's calls.
    * ``power_cycle()`` and :meth:`inject_reset` reset the chip: RAM parameters come
      from the flash (all zero, Stm 1, if it was never written), jobs go to 0 (motor
      power off), counters read 0 wherever the shafts are, flags clear, a partial
      packet is lost, the baud rate returns to the jumpers'. Shafts keep their angle.
    * ``baud`` changes right after the SetBaud reply is returned; a carrier that can
      change its rate should follow it.

    ``hardware``: one :class:`AxisHardware` per axis (default: three unloaded
    motors). ``flash_path``: JSON file that plays the flash (``None``: in memory,
    lost with the object). ``jumper_baud``: the rate set by J3..J1.
    """

    def __init__(
        self,
        hardware: Sequence[AxisHardware] | None = None,
        *,
        flash_path: Path | str | None = None,
        jumper_baud: int = DEFAULT_BAUD,
    ) -> None:
        hardware = list(hardware) if hardware is not None else [AxisHardware()] * AXES
        if len(hardware) != AXES:
            raise ValueError(f"the Z1100 has {AXES} axes, got {len(hardware)} hardware entries")
        if jumper_baud not in BAUD_RATES:
            raise ValueError(f"jumper_baud must be one of {BAUD_RATES}, got {jumper_baud}")
        self.jumper_baud = jumper_baud
        self._flash = _Flash(Path(flash_path) if flash_path is not None else None)
        self._axes = [_Axis(i, hw) for i, hw in enumerate(hardware)]
        self._decoder = RequestDecoder()
        self._packet_start_s = 0.0
        self._outbox = bytearray()
        # inject_corrupt_codes: replies (to which command: None, any) still to send
        # with their code byte corrupted, and the bits flipped
        self._corrupt_replies = 0
        self._corrupt_command: int | None = None
        self._corrupt_mask = 0
        self._time_s = 0.0
        self._tick = 0
        self.baud = jumper_baud
        self._reset()

    @classmethod
    def with_loads(
        cls,
        load_inertias_kg_m2: Sequence[float],
        *,
        flash_path: Path | str | None = None,
        jumper_baud: int = DEFAULT_BAUD,
    ) -> Z1100Chip:
        """Three default motors carrying these extra load inertias."""
        hardware = [AxisHardware(load_inertia_kg_m2=j) for j in load_inertias_kg_m2]
        return cls(hardware, flash_path=flash_path, jumper_baud=jumper_baud)

    # --- observation ---------------------------------------------------------------------

    @property
    def time_s(self) -> float:
        """Simulation time reached."""
        return self._time_s

    @property
    def samples_run(self) -> int:
        """Servo samples computed so far (idle samples skipped are not counted)."""
        return sum(a.samples for a in self._axes)

    @property
    def busy_pin(self) -> int:
        """The BUSY output level: 0 while any motor that drives it (SetBusy) is
        running, 1 otherwise (also when no motor drives it)."""
        return 0 if any(a.running and a.p.busy for a in self._axes) else 1

    @property
    def motors(self) -> tuple[DcMotor, ...]:
        """The plants (set ``external_torque_nm`` for a load torque)."""
        return tuple(a.motor for a in self._axes)

    def axis_state(self, axis: int) -> AxisState:
        """A snapshot of one axis (0..2)."""
        return self._axis(axis).state()

    def parameters(self, axis: int) -> AxisParameters:
        """A copy of one axis's RAM parameters."""
        return replace(self._axis(axis).p)

    def free(self, axis: int) -> None:
        """What SetJob 0 does to motor ``axis`` (0..2): power off, the shaft free."""
        self._set_job(self._axis(axis), int(Job.FREE))

    def _axis(self, axis: int) -> _Axis:
        if not 0 <= axis < AXES:
            raise ValueError(f"axis must be 0..{AXES - 1}, got {axis}")
        return self._axes[axis]

    # --- faults --------------------------------------------------------------------------

    def power_cycle(self, address: int | None = None) -> None:
        """Switch the supply off and on (``address`` is ignored: one chip per line)."""
        self._reset()

    def inject_reset(self) -> None:
        """An unexpected reset (EMI from motor switching, the manual's hint): RAM
        parameters are lost. They read 0 (GetKABH, GetVmax, GetAcc) unless SetFlash
        stored some, which the restarting firmware loads, as at power-on."""
        self._reset()

    def inject_noise_reply(self) -> None:
        """Line noise reached the chip's receiver: it answers a packet nobody sent
        (code bit 3, data 0). Sent at the next ``advance_to``."""
        self._outbox += self._reply(ReplyCode.COMMUNICATION)

    def inject_corrupt_codes(self, n: int, mask: int = 0x10, command: int | None = None) -> None:
        """A noisy line from the chip: the code byte of the next ``n`` replies (to the
        command byte ``command`` only, if given) arrives with the bits of ``mask``
        flipped (data and checksum as sent); e.g. 0x10 makes an OK read as "forbidden
        while motor 1 moves" to a host that did not check the sum."""
        if n < 0 or not 0 < mask <= 0xFF:
            raise ValueError("n must be >= 0 and mask 1..255")
        self._corrupt_replies, self._corrupt_mask = n, mask
        self._corrupt_command = command

    def jam(self, axis: int, jammed: bool = True) -> None:
        """Seize (or free) an axis's mechanism: friction far above the stall torque,
        so the servo error grows until the error limit cuts the power."""
        a = self._axis(axis)
        base = a.params_base
        a.motor.params = replace(base, coulomb_friction_nm=_JAM_FRICTION_NM) if jammed else base
        if jammed:
            a.motor.speed_rad_s = 0.0
        a.wake()

    def _reset(self) -> None:
        stored = self._flash.load()
        for i, a in enumerate(self._axes):
            a.p = replace(stored[i]) if stored is not None else AxisParameters()
            a.reset()
            a.next_tick = self._tick + 1
        self._decoder.clear()
        self._outbox.clear()
        self.baud = self.jumper_baud

    # --- SimDevice -----------------------------------------------------------------------

    def advance_to(self, t_s: float) -> bytes:
        """Run the servo loops up to ``t_s``; returns bytes sent unasked (see class)."""
        if t_s > self._time_s:
            self._expire_packet(t_s)
            due = math.floor(t_s / STM_TICK_S + _TICKS_EPS)
            if due > self._tick:
                for a in self._axes:
                    a.run_until(due)
                self._tick = due
            self._time_s = t_s
        if not self._outbox:
            return b""
        data = bytes(self._outbox)
        self._outbox.clear()
        return data

    def receive(self, byte: int) -> bytes:
        """One host byte has arrived (see class); returns the reply, if any."""
        out = bytearray()
        self._expire_packet(self._time_s)
        out += self._outbox  # an expired packet's reply goes first
        self._outbox.clear()
        was_idle = self._decoder.pending == 0
        events = self._decoder.feed(bytes((byte & 0xFF,)))
        if was_idle and self._decoder.pending:
            self._packet_start_s = self._time_s
        for event in events:
            if isinstance(event, BadRequest):
                out += self._reply(ReplyCode.CHECKSUM)
                continue
            reply = self._execute(event)
            if self._corrupt_replies and self._corrupt_command in (None, event.command_byte):
                self._corrupt_replies -= 1
                reply = bytes((reply[0] ^ self._corrupt_mask, *reply[1:]))
            out += reply
        return bytes(out)

    def _expire_packet(self, now_s: float) -> None:
        if self._decoder.pending and now_s - self._packet_start_s >= PACKET_TIMEOUT_S:
            self._decoder.clear()  # the chip drops the bytes but still answers
            self._outbox += self._reply(ReplyCode.TIMEOUT)

    # --- command execution ---------------------------------------------------------------

    def _reply(self, code: ReplyCode, data: int = 0) -> bytes:
        if any(a.stalled for a in self._axes):
            code |= ReplyCode.STALL
        return encode_reply(Reply(code, data))

    def _execute(self, request: Request) -> bytes:
        command = request.command
        if command is None:
            return self._reply(ReplyCode.UNKNOWN_COMMAND)
        axis = request.axis
        info = COMMANDS[command]
        data = request.data
        if info.forbidden_while_moving:
            refused = self._refusal(command, axis, data)
            if refused:
                return self._reply(refused)
        if command.is_get:
            return self._reply(ReplyCode.OK, self._read(command, axis))
        for a in self._axes:
            a.wake()  # any write may change what an idle axis does
        new_baud = self._write(command, axis, data)
        reply = self._reply(ReplyCode.OK)
        if new_baud is not None:
            self.baud = new_baud  # after the reply: it still goes out at the old rate
        return reply

    def _refusal(self, command: Command, axis: int | None, data: int) -> ReplyCode:
        """The "forbidden while motor n is moving" bits for a command, or OK."""
        if command is Command.SET_START:
            code = ReplyCode.OK
            for index in unpack_axes(data):
                if self._axes[index].running:
                    code |= moving_flag(index)
            return code
        assert axis is not None  # every other forbidden-while-moving command is per axis
        if command is Command.SET_JOB and data & 0xFF == Job.FREE:
            return ReplyCode.OK  # job 0 (power off) is allowed while moving
        return moving_flag(axis) if self._axes[axis].running else ReplyCode.OK

    def _read(self, command: Command, axis: int | None) -> int:
        if command is Command.GET_START:
            return pack_start(
                StartStatus(
                    frozenset(i for i, a in enumerate(self._axes) if a.running),
                    frozenset(i for i, a in enumerate(self._axes) if a.direction_positive),
                )
            )
        if command in (Command.GET_STOP, Command.GET_ESTOP):
            return pack_stop(
                StopStatus(
                    frozenset(i for i, a in enumerate(self._axes) if a.stopped_by_command),
                    frozenset(i for i, a in enumerate(self._axes) if a.stalled),
                )
            )
        assert axis is not None
        a = self._axes[axis]
        p = a.p
        if command is Command.GET_KABH:
            return pack_kab(p.kabh)
        if command is Command.GET_KABD:
            return pack_kab(p.kabd)
        if command is Command.GET_VMAX:
            return p.vmax_counts_s
        if command is Command.GET_ACC:
            return p.acc_counts_s2
        if command is Command.GET_STM:
            return p.stm
        if command is Command.GET_HVM:
            return p.hvm_counts_s
        if command is Command.GET_HAC:
            return p.hac_counts_s2
        if command is Command.GET_LIMIT:
            return p.limit_counts  # D1:D0; D3:D2 read 0 (errata decision)
        if command is Command.GET_CAB:
            return p.cab
        if command is Command.GET_JOB:
            return a.job
        if command is Command.GET_BUSY:
            return int(p.busy)
        if command is Command.GET_TARGET:
            return pack_int32(a.target_counts)
        if command is Command.GET_ENCODER:
            a.sync_counter()
            return a.counter & 0xFFFF_FFFF  # a 32-bit counter wraps
        if command is Command.GET_ERROR:
            return pack_error(max(INT16_MIN, min(INT16_MAX, a.error)))  # saturates
        if command is Command.GET_SWITCH:
            return int(a.switch_pressed)
        raise AssertionError(f"no reader for {command!r}")

    def _write(self, command: Command, axis: int | None, data: int) -> int | None:
        """Execute a Set; returns a new baud rate for SetBaud, else None.

        Bits outside a command's documented field are ignored, and values the chip
        cannot use are stored as sent (the chip has no "bad value" bit; the codec's
        builders refuse them before they are sent).
        """
        if command is Command.SET_START:
            self._start(data)
        elif command is Command.SET_STOP:
            for index in unpack_axes(data):
                a = self._axes[index]
                # Stop acts only on a motor turning in the velocity job.
                if a.running and a.mode == _VELOCITY:
                    a.stopping = True
                    a.stopped_by_command = True
        elif command is Command.SET_ESTOP:
            for index in unpack_axes(data):
                a = self._axes[index]
                if a.running:
                    # Stop at once: the reference jumps to where the shaft is and the
                    # servo brakes as hard as it can (the manual's "hard jolt").
                    a.sync_counter()
                    a.finish()
                    a.ref = float(a.counter)
                    a.stopped_by_command = True
        elif command is Command.SET_CLR:
            for a in self._axes:
                a.stalled = False  # the motor stays unpowered until Start or Job
        elif command is Command.SET_BAUD:
            # A rate the jumpers cannot select is ignored (no reply bit says so).
            return data if data in BAUD_RATES else None
        elif command is Command.SET_FLASH:
            self._flash.save([a.p for a in self._axes])
        else:
            assert axis is not None
            self._write_axis(command, self._axes[axis], data)
        return None

    def _write_axis(self, command: Command, a: _Axis, data: int) -> None:
        p = a.p
        if command is Command.SET_KABH:
            p.kabh = p.kabd = unpack_kab(data)  # KABH also overwrites KABD (manual)
        elif command is Command.SET_KABD:
            p.kabd = unpack_kab(data)
        elif command is Command.SET_VMAX:
            p.vmax_counts_s = data
        elif command is Command.SET_ACC:
            p.acc_counts_s2 = data
        elif command is Command.SET_STM:
            old_s = a.sample_s
            p.stm = data & 0xFF
            a.ref_v *= a.sample_s / old_s  # keep the profile speed in counts/s
        elif command is Command.SET_HVM:
            p.hvm_counts_s = data
        elif command is Command.SET_HAC:
            p.hac_counts_s2 = data
        elif command is Command.SET_LIMIT:
            p.limit_counts = min(data & 0xFFFF, LIMIT_MAX_COUNTS)
        elif command is Command.SET_CAB:
            a.sync_counter()  # counts so far keep the old direction
            p.cab = data & CAB_MASK
            a.update_signs()
        elif command is Command.SET_JOB:
            self._set_job(a, data & 0xFF)
        elif command is Command.SET_BUSY:
            p.busy = bool(data & 1)
        elif command is Command.SET_TARGET:
            a.target_counts = unpack_int32(data)
        elif command is Command.SET_ZERO:
            self._zero(a)
        else:
            raise AssertionError(f"no writer for {command!r}")

    @staticmethod
    def _set_job(a: _Axis, job: int) -> None:
        a.job = job
        a.stalled = False  # "earlier errors are cleared"
        if job in (Job.TARGET, Job.VELOCITY):
            if not a.powered:
                a.engage()  # servo on, holding where the shaft is
        else:
            # Job 0 frees the shaft; "undefined" jobs (1, 4..255) do the same.
            a.power_off()

    @staticmethod
    def _ready(a: _Axis, *, homing: bool) -> bool:
        """The manual: K, A, B, Vmax, Acc, the error limit and the home speed must be
        non-zero before Start. Decision: a motor that misses one is simply not
        started - the reply is still OK (no bit exists for it) and its GetStart bit
        stays 0, which the host can check. Zero needs Hac instead of Vmax/Acc."""
        p = a.p
        gains = p.kabh
        common = gains.k and gains.a and gains.b and p.limit_counts and _positive(p.hvm_counts_s)
        if not common or a.job not in (Job.TARGET, Job.VELOCITY):
            return False
        if homing:
            return _positive(p.hac_counts_s2) > 0
        return _positive(p.vmax_counts_s) > 0 and _positive(p.acc_counts_s2) > 0

    def _start(self, data: int) -> None:
        request = unpack_start(data)
        for index in request.running:
            a = self._axes[index]
            if not self._ready(a, homing=False):
                continue
            a.stalled = False  # starting the motor clears its stall error
            a.stopped_by_command = False
            a.direction_positive = index in request.positive
            if not a.powered:
                a.engage()
            a.running = True
            a.stopping = False
            a.mode = _MOVE if a.job == Job.TARGET else _VELOCITY

    def _zero(self, a: _Axis) -> None:
        if not self._ready(a, homing=True):
            return
        a.stalled = False
        a.stopped_by_command = False
        if not a.powered:
            a.engage()
        a.running = True
        a.stopping = False
        a.mode = _HOME
        a.home_phase = _H_LEAVE if a.switch_pressed else _H_SEEK
