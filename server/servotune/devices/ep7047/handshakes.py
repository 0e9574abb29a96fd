"""The command handshakes of the EP7047-1032 cycle, sans-IO: urgent requests (STOP,
emergency stop, Halt), starts and their Execute/Busy handshake, Enable/Reset, the
diagnosis watch and the end of a move. See ``servotune.devices.ep7047.link`` for the
rules (the module docstring's "Decisions").

``Handshakes`` holds the cycle state (``state``: the outputs to send, what is known of
the drive) and does no I/O: the cycle gives it the requests (a ``RequestQueue``), the
inputs of each exchange and the time, sends ``state.outputs()``, reads the diagnosis
word when ``diag_due`` asks for it, and the handshakes report results and events
through ``HandshakeReports``. Called from one thread at a time (the cycle's).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Protocol

from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import (
    CHANGE_START_TYPES,
    MODULO_START_TYPES,
    Inputs,
    PosDiag,
    SdoObject,
    StartType,
    StmStatus,
)
from servotune.devices.ep7047.modulo import ModuloError, modulo_travel
from servotune.devices.ep7047.requests import (
    _CALIBRATION_MOVES,
    _ENDLESS_TYPES,
    _SDO_KINDS,
    CycleCounters,
    RequestQueue,
    _CycleState,
    _Exec,
    _Kind,
    _Request,
    _state_label,
    _StopPhase,
    diag_text,
)
from servotune.link.base import DeviceRefusedError
from servotune.schema import EventLevel


class HandshakeReports(Protocol):
    """What the handshakes tell the event loop: results of requests and events."""

    def post_event(self, level: EventLevel, message: str, *, axis: bool = True) -> None: ...

    def resolve(self, request: _Request, result: object = None) -> None: ...

    def reject(self, request: _Request, error: BaseException) -> None: ...


class Handshakes:
    """The command handshakes of one drive (see the module docstring).

    ``coe`` is the cycle's record of CoE values (last read or written; the emergency
    deceleration and the modulo settings are read from it), ``counters`` the link's
    counters (a watchdog drop counts).
    """

    def __init__(
        self,
        *,
        cycle_s: float,
        queue: RequestQueue,
        reports: HandshakeReports,
        coe: Mapping[SdoObject, int],
        counters: CycleCounters,
    ) -> None:
        self._cycle_s = cycle_s
        self._queue = queue
        self._reports = reports
        self._coe = coe
        self._counters = counters
        self.state = _CycleState()

    def reset(self) -> _CycleState:
        """Start from zero outputs and nothing known (a bring-up, a shutdown)."""
        self.state = _CycleState()
        return self.state

    def drop_outputs(self, gap_s: float, watchdog_s: float) -> None:
        """No good process data for ``gap_s`` (about the slave's watchdog ``watchdog_s``):
        the slave has dropped its outputs (Enable off, the move aborted); never re-assert
        them silently - drop them here too, and say so."""
        cs = self.state
        if not (cs.enable or cs.execute or cs.emergency):
            return
        if cs.pending is not None:
            self._reports.reject(
                cs.pending, DeviceRefusedError("no process data for too long: the drive dropped it")
            )
            cs.pending = None
        cs.enable = cs.execute = cs.emergency = cs.reset = False
        cs.stop_phase = _StopPhase.NONE
        self._drop_execute()
        self._counters.errors += 1
        self._counters.watchdog_trips += 1
        self._reports.post_event(
            "error",
            f"no good process data for {gap_s * 1000:.0f} ms (the drive's watchdog is "
            f"{watchdog_s * 1000:.0f} ms): the drive dropped Enable because process "
            "data stopped (or was about to) - the motor stops without holding torque, its "
            "settings are kept; Enable is off - press Enable to continue",
        )

    # --- requests (thread side) ---------------------------------------------------------

    def take_urgent(self, now: float) -> None:
        """Apply the queued urgent requests (STOP, Emergency stop, Halt) to this cycle's
        outputs."""
        for request in self._queue.take_urgent():
            if request.kind is _Kind.HALT:
                self._apply_halt(request)
            else:
                self._apply_stop(request, now)

    def _apply_stop(self, request: _Request, now: float) -> None:
        cs = self.state
        label = "STOP" if request.kind is _Kind.STOP else "Emergency stop"
        error = DeviceRefusedError(f"not sent: {label} came first")
        if cs.pending is not None:
            self._reports.reject(cs.pending, DeviceRefusedError(f"aborted by {label}"))
            cs.pending = None
        for queued in self._queue.drop_commands():
            self._reports.reject(queued, error)
        cs.reset = False
        self._drop_execute()
        if cs.enable:
            cs.emergency = True
            cs.stop_phase = (
                _StopPhase.STOPPING if request.kind is _Kind.STOP else _StopPhase.EMCY_HOLD
            )
            emergency_ms = self._coe.get(codec.EMERGENCY_DECELERATION, 1000)
            cs.stop_deadline = now + emergency_ms / 1000 + 0.5
            cs.stop_cycles = 0
        cs.after_exchange.append(request)

    def _apply_halt(self, request: _Request) -> None:
        cs = self.state
        if cs.pending is not None and cs.pending.kind is _Kind.START:
            self._reports.reject(
                cs.pending, DeviceRefusedError("halted before the drive took the move")
            )
            cs.pending = None
        self._drop_execute()
        cs.after_exchange.append(request)

    def _drop_execute(self) -> None:
        """Execute low now; a move that may have started is watched until Busy falls."""
        cs = self.state
        cs.execute = False
        if cs.exec_state is _Exec.ARMING:  # Execute never rose: nothing started
            cs.exec_state = _Exec.IDLE
            cs.running = None
        elif cs.exec_state is not _Exec.IDLE:
            cs.exec_state = _Exec.HALTING

    def take_normal(self, now: float) -> None:
        """Take the next request that is still wanted: an SDO transfer becomes
        ``state.sdo_job`` (the cycle runs it), a command begins."""
        cs = self.state
        while True:
            request = self._queue.pop_normal()
            if request is None:
                return
            if request.future.done():  # the caller gave up
                continue
            if request.kind in _SDO_KINDS:
                cs.sdo_job = request
                return
            self._begin_command(request, now)
            return

    def _begin_command(self, request: _Request, now: float) -> None:
        cs = self.state
        kind = request.kind
        if kind is _Kind.ENABLE:
            if cs.stop_phase is _StopPhase.STOPPING:
                self._reports.reject(
                    request, DeviceRefusedError("a STOP is in progress: wait for it")
                )
                return
            cs.enable = True
            request.deadline = now + 0.5
            cs.pending = request
        elif kind is _Kind.DISABLE:
            cs.enable = cs.emergency = cs.reset = False
            cs.stop_phase = _StopPhase.NONE
            self._drop_execute()
            cs.after_exchange.append(request)
        elif kind is _Kind.RESET:
            if cs.inputs.busy:
                self._reports.reject(
                    request,
                    DeviceRefusedError(
                        "Reset is ignored while Busy: wait for the move to end or stop it"
                    ),
                )
                return
            cs.reset = True
            request.count = max(2, math.ceil(0.01 / self._cycle_s))
            cs.pending = request
        elif kind is _Kind.START:
            self._begin_start(request, now)
        else:  # pragma: no cover - urgent kinds never reach the normal queue
            self._reports.reject(request, DeviceRefusedError(f"unexpected request {kind}"))

    def _refuse_start(self, request: _Request) -> str | None:
        """Why the drive would refuse this start now (the server knows it), or None."""
        cs = self.state
        inputs = cs.inputs
        start_type = request.start_type
        if cs.stop_phase is not _StopPhase.NONE:
            return "a STOP / emergency stop is in progress: wait until it has ended"
        if not cs.enable or not inputs.stm_status & StmStatus.READY:
            return "the drive is not enabled: press Enable first (the drive answers Error)"
        if start_type in CHANGE_START_TYPES:
            if cs.exec_state is not _Exec.RUNNING or not inputs.busy:
                return (
                    f"{start_type.name} changes a running move, but Execute is low (no move "
                    "runs): start it with a plain start type"
                )
            if cs.running in _CALIBRATION_MOVES:
                return f"{start_type.name} cannot change a calibration"
            if start_type is StartType.ADDITIVE_CHANGE and cs.running in _ENDLESS_TYPES:
                return "ADDITIVE_CHANGE needs an active target; an ENDLESS move has none"
            return None
        if cs.exec_state is not _Exec.IDLE or inputs.busy:
            return (
                "a move is running (Busy): wait for it to end, Halt it, or change it with a "
                "_CHANGE start type"
            )
        if start_type in MODULO_START_TYPES:
            modulo = self._coe.get(codec.MODULO_FACTOR, 0)
            if modulo <= 0:
                return "the modulo factor (0x8020:0E) is 0: set 'Modulo factor' first"
            if request.target < 0:
                return (
                    f"modulo targets are 0 or more (each whole {modulo} adds a turn); got "
                    f"{request.target}"
                )
            short = start_type in (StartType.MODULO_SHORT, StartType.MODULO_SHORT_EXT)
            if short and request.target >= modulo:
                return (
                    f"{start_type.name} needs a target in 0..{modulo - 1} (modulo factor "
                    f"{modulo}); got {request.target}"
                )
        return None

    def _begin_start(self, request: _Request, now: float) -> None:
        cs = self.state
        reason = self._refuse_start(request)
        if reason is not None:
            self._reports.reject(request, DeviceRefusedError(reason))
            return
        cs.target = request.target
        cs.velocity_bp = request.velocity_bp
        cs.start_type = int(request.start_type)
        cs.acceleration_ms = request.acceleration_ms
        cs.deceleration_ms = request.deceleration_ms
        request.previous_target = cs.target_estimate
        cs.target_estimate = self._estimate_target(request.start_type, request.target)
        request.diag_before = cs.diag
        cs.pending = request
        if request.start_type in CHANGE_START_TYPES:
            request.deadline = now + max(10 * self._cycle_s, 0.025)
            request.stage = 1  # a change: Execute stays high
            return
        cs.exec_state = _Exec.ARMING
        cs.running = request.start_type

    def _estimate_target(self, start_type: StartType, operand: int) -> float | None:
        cs = self.state
        actual = cs.inputs.actual_position_counts
        if start_type in (StartType.ABSOLUTE, StartType.ABSOLUTE_CHANGE):
            return float(operand)
        if start_type in (StartType.RELATIVE, StartType.RELATIVE_CHANGE):
            return float(actual + operand)
        if start_type is StartType.ADDITIVE:
            base = cs.last_target if cs.last_target is not None else actual
            return base + operand
        if start_type is StartType.ADDITIVE_CHANGE:
            base = cs.target_estimate if cs.target_estimate is not None else actual
            return base + operand
        if start_type in MODULO_START_TYPES:
            try:
                travel, _ = modulo_travel(
                    start_type,
                    actual,
                    operand,
                    self._coe.get(codec.MODULO_FACTOR, 0),
                    self._coe.get(codec.MODULO_TOLERANCE_WINDOW, 0),
                    cs.last_direction,
                )
            except ModuloError:
                return None
            return float(actual + travel)
        return None  # ENDLESS, calibration: no target

    def before_exchange(self, now: float) -> None:
        """What an earlier cycle prepared: Execute rises after ARMING, Reset pulses."""
        cs = self.state
        if cs.exec_state is _Exec.ARMING:
            cs.execute = True
            cs.exec_state = _Exec.WAIT_BUSY
            cs.move_started_t = now
            if cs.pending is not None:
                cs.pending.deadline = now + max(10 * self._cycle_s, 0.025)
        pending = cs.pending
        if pending is not None and pending.kind is _Kind.RESET and pending.stage == 0:
            pending.count -= 1
            if pending.count < 0:
                cs.reset = False
                pending.stage = 1
                pending.count = 3

    # --- evaluation after an exchange ---------------------------------------------------

    def diag_due(self, previous: Inputs, inputs: Inputs, now: float) -> bool:
        """Whether the diagnosis word (0x9020:01) must be read now: Warning rose (or
        Error), a change is being watched, or the last read is older than 0.1 s. Without
        Warning the diagnosis is cleared and nothing is read."""
        cs = self.state
        if not inputs.warning:
            cs.diag = PosDiag.NONE
            return False
        pending = cs.pending
        watching_change = pending is not None and pending.stage == 1
        rose = not previous.warning or (inputs.error and not previous.error)
        return rose or watching_change or now - cs.diag_t > 0.1

    def take_diag(self, status_word: int, now: float) -> None:
        """The diagnosis word (0x9020:01) read at ``now``."""
        cs = self.state
        cs.diag = PosDiag(status_word & 0x7)
        cs.diag_t = now

    def advance_stop(self, inputs: Inputs, now: float) -> None:
        cs = self.state
        if cs.stop_phase is _StopPhase.NONE:
            return
        cs.stop_cycles += 1
        standstill = not inputs.busy and inputs.actual_velocity_bp == 0
        if cs.stop_cycles < 3 or not (standstill or now > cs.stop_deadline):
            return
        cs.emergency = False
        position = inputs.actual_position_counts
        if cs.stop_phase is _StopPhase.STOPPING:
            cs.enable = False
            self._reports.post_event("warning", f"STOP: stopped at {position} counts, Enable off")
        else:
            self._reports.post_event(
                "warning", f"Emergency stop: stopped at {position} counts, Enable kept"
            )
        cs.stop_phase = _StopPhase.NONE

    def advance_exec(self, inputs: Inputs, now: float) -> None:
        """Execute: held while the move runs, dropped once Busy has risen and fallen."""
        cs = self.state
        if cs.exec_state in (_Exec.RUNNING, _Exec.HALTING) and not inputs.busy:
            pending = cs.pending
            if pending is not None and pending.kind is _Kind.START and pending.stage == 1:
                return  # a change is being watched: advance_pending ends it first
            halted = cs.exec_state is _Exec.HALTING
            cs.execute = False
            cs.exec_state = _Exec.IDLE
            self._finish_move(inputs, now, halted=halted)

    def _finish_move(self, inputs: Inputs, now: float, *, halted: bool) -> None:
        cs = self.state
        running = cs.running
        cs.running = None
        if running is None:
            return
        if running in _ENDLESS_TYPES or running in _CALIBRATION_MOVES:
            cs.last_target = float(inputs.actual_position_counts)
        elif cs.target_estimate is not None:
            cs.last_target = cs.target_estimate
            if cs.target_estimate != inputs.actual_position_counts:
                cs.last_direction = 1 if cs.target_estimate > inputs.actual_position_counts else -1
        seconds = now - cs.move_started_t
        where = f"at {inputs.actual_position_counts} counts after {seconds:.2f} s"
        ok, text = self._end_outcome(running, inputs)
        if halted:
            level: EventLevel = "info" if running in _ENDLESS_TYPES else "warning"
            text = f"{running.name} halted {where}" + ("" if ok else f": {text}")
        elif ok:
            level = "info"
            text = f"{running.name} ended {where}: {text}"
        else:
            level = "error" if inputs.error else "warning"
            text = f"{running.name} ended {where}: {text}"
        self._reports.post_event(level, text)

    def _end_outcome(self, start_type: StartType, inputs: Inputs) -> tuple[bool, str]:
        cs = self.state
        if inputs.error:
            detail = diag_text(cs.diag) if cs.diag else self._error_hint(start_type)
            return False, f"the drive answered Error: {detail}"
        calibrated = bool(inputs.pos_status & codec.PosStatus.CALIBRATED)
        if start_type in (StartType.SET_CALIBRATION, *_CALIBRATION_MOVES):
            if calibrated:
                return True, "Calibrated"
            return False, "Calibrated is not set: " + (
                diag_text(cs.diag) if cs.diag else "calibration did not complete"
            )
        if start_type is StartType.CLEAR_CALIBRATION:
            return (not calibrated), ("Calibrated cleared" if not calibrated else "still set")
        if start_type in _ENDLESS_TYPES:
            return True, "stopped"
        if inputs.in_target:
            return True, "In-Target" + (f" (Warning: {diag_text(cs.diag)})" if cs.diag else "")
        if cs.diag & PosDiag.COMMAND_REJECTED:
            return False, f"the drive set Warning: {diag_text(cs.diag)}"
        if cs.diag:
            return False, diag_text(cs.diag)
        return False, (
            "not In-Target: the motor was not in the target window within the In-Target timeout"
        )

    def _error_hint(self, start_type: StartType) -> str:
        if start_type in MODULO_START_TYPES:
            return "modulo factor or modulo target out of range"
        state = self.state.drive_state
        named = f" (last drive state {_state_label(state)})" if state is not None else ""
        return f"no diagnosis bit set{named}"

    def advance_pending(self, inputs: Inputs, now: float) -> None:
        cs = self.state
        request = cs.pending
        if request is None:
            return
        if request.kind is _Kind.ENABLE:
            if inputs.stm_status & StmStatus.READY:
                cs.pending = None
                self._reports.resolve(request, "enabled")
            elif now > request.deadline:
                cs.pending = None
                cs.enable = False
                self._reports.reject(
                    request,
                    DeviceRefusedError(
                        "the drive did not report STM Ready within 0.5 s after Enable: check "
                        "the motor supply and STM error; Enable dropped again"
                    ),
                )
        elif request.kind is _Kind.RESET:
            if request.stage == 1:
                request.count -= 1
                if request.count <= 0:
                    cs.pending = None
                    still = [
                        name
                        for name, flag in (
                            ("Error", inputs.error),
                            ("Warning", inputs.warning),
                            ("STM error", bool(inputs.stm_status & StmStatus.ERROR)),
                        )
                        if flag
                    ]
                    if still:
                        self._reports.reject(
                            request,
                            DeviceRefusedError(
                                f"{' and '.join(still)} still set after Reset: {diag_text(cs.diag)}"
                            ),
                        )
                    else:
                        cs.diag = PosDiag.NONE
                        self._reports.resolve(request, "cleared")
        elif request.kind is _Kind.START:
            if request.stage == 1:
                self._watch_change(request, inputs, now)
            else:
                self._watch_start(request, inputs, now)

    def _watch_start(self, request: _Request, inputs: Inputs, now: float) -> None:
        """WAIT_BUSY: the drive has taken the move once Busy is seen twice without Error."""
        cs = self.state
        if cs.exec_state is _Exec.ARMING:
            return
        if inputs.busy:
            request.saw_busy = True
            request.count += 1
            if request.count >= 2 and not inputs.error:
                cs.exec_state = _Exec.RUNNING
                cs.pending = None
                self._reports.resolve(request, f"{request.start_type.name} started")
            return
        if not request.saw_busy and now <= request.deadline:
            return
        # Busy rose and fell already, or never showed: the command is over.
        cs.pending = None
        cs.execute = False
        cs.exec_state = _Exec.IDLE
        ok, text = self._end_outcome(request.start_type, inputs)
        cs.running = None
        if not ok:
            cs.target_estimate = request.previous_target
            self._reports.reject(request, DeviceRefusedError(f"{request.start_type.name}: {text}"))
        else:
            self._reports.resolve(request, f"{request.start_type.name} done: {text}")

    def _watch_change(self, request: _Request, inputs: Inputs, now: float) -> None:
        cs = self.state
        new = cs.diag & ~request.diag_before
        if new & PosDiag.COMMAND_REJECTED:
            cs.pending = None
            cs.target_estimate = request.previous_target
            self._reports.reject(
                request,
                DeviceRefusedError(
                    f"{request.start_type.name}: the drive rejected the change: "
                    f"{diag_text(PosDiag.COMMAND_REJECTED)}"
                ),
            )
        elif not inputs.busy or now > request.deadline:
            cs.pending = None
            note = f"; {diag_text(PosDiag.TARGET_OVERRUN)}" if new & PosDiag.TARGET_OVERRUN else ""
            self._reports.resolve(request, f"{request.start_type.name} taken{note}")
