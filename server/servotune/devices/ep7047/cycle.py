"""The EP7047-1032 cycle: the thread that owns the master - bring-up, the cyclic
exchange to an absolute deadline, the working-counter check, SDO slots, the samples and
the shutdown. It has the command handshakes (``devices.ep7047.handshakes``, sans-IO) and
tells the event loop what happens through ``CycleReports``, declared here. See
``servotune.devices.ep7047.link`` for the design ("The owner: one cycle thread").
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import threading
import time
from collections.abc import Callable, Mapping
from typing import Final, Protocol

from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import (
    CodecError,
    Inputs,
    PosSettings,
    PosStatus,
    SdoObject,
    StmStatus,
)
from servotune.devices.ep7047.descriptor import INVERSION_BITS, INVERSION_PARAMETER, PARAMETER_SDO
from servotune.devices.ep7047.handshakes import HandshakeReports, Handshakes
from servotune.devices.ep7047.requests import (
    _DIAG_BITS,
    _POS_BITS,
    _STM_BITS,
    AL_WATCHDOG,
    CYCLE_THREAD_NICE,
    STATE_ACTIVE_S,
    VALUE_ABORT_CODES,
    WATCHDOG_MARGIN_S,
    CycleCounters,
    RequestQueue,
    SdoValueRefusedError,
    _BringUpError,
    _DropOutError,
    _Exec,
    _Kind,
    _Request,
    _StopPhase,
    watchdog_trip_text,
)
from servotune.link.base import (
    DeviceRefusedError,
    DeviceTimeoutError,
    LinkDownError,
    ProtocolError,
    Sample,
)
from servotune.schema import AxisHealth, EventLevel, LinkState
from servotune.transports.ethercat import (
    INIT_STATE,
    OP_STATE,
    PREOP_STATE,
    SAFEOP_STATE,
    STATE_ACK,
    STATE_ERROR,
    EthercatError,
    EthercatMailboxError,
    EthercatMaster,
    EthercatSdoError,
    EthercatSlave,
    EthercatUnavailableError,
    PacedMaster,
    al_status_text,
    state_name,
)

_POS_WARNING = int(PosStatus.WARNING)

logger = logging.getLogger(__name__)


_STM_SHOWN: Final = 0xFFFF & ~int(StmStatus.TXPDO_TOGGLE)


class CycleReports(HandshakeReports, Protocol):
    """What the cycle tells the event loop (``devices.ep7047.bridge.EventLoopBridge``
    implements it). Calls come from the cycle thread, in order; each post is delivered
    after the samples posted before it."""

    def post_state(self, state: LinkState, message: str) -> None: ...

    def post_health(self, health: AxisHealth, message: str) -> None: ...

    def post_params(self, values: Mapping[str, int], source: str) -> None: ...

    def post_sample(self, sample: Sample) -> None:
        """May be held back to be posted in a batch with the next samples."""
        ...

    def flush_samples(self) -> None:
        """Post the samples held back so far."""
        ...

    def begin_cycle(self) -> None:
        """Results of requests from here on wait for ``end_cycle``."""
        ...

    def end_cycle(self) -> None:
        """Post the results held since ``begin_cycle``, after this cycle's sample."""
        ...


class Cycle:
    """The owner of one EtherCAT master and its slave's process data: ``run(master)`` is
    the cycle thread (see the module docstring). It has the command ``handshakes`` and
    reports through ``CycleReports``; the event loop hands it requests through the
    ``RequestQueue`` and stops it with ``halt``."""

    def __init__(
        self,
        link_id: str,
        ifname: str,
        slave: int,
        *,
        queue: RequestQueue,
        reports: CycleReports,
        counters: CycleCounters,
        cycle_s: float,
        speed_range_steps_s: int,
        settings: PosSettings | None,
        clock: Callable[[], float],
        state_poll_s: float,
        rest_state_poll_s: float,
        max_lost_frames: int,
        reconnect_max_s: float,
        watchdog_s: float,
    ) -> None:
        self.id = link_id
        self._ifname = ifname
        self._slave_pos = slave
        self._queue = queue
        self._reports = reports
        self._counters = counters
        self._cycle_s = cycle_s
        self._speed_range = speed_range_steps_s
        self._clock = clock
        # The drive state (0xA010:11) is only in the mailbox: one SDO per read. Read every
        # state_poll_s while the drive does something (Busy, Execute, a STOP ramp, or
        # within STATE_ACTIVE_S of any status flag changing), every rest_state_poll_s
        # at rest, where it does not change by itself: the state timeline keeps its
        # 10 ms detail where there is detail, and a real drive's mailbox (and this
        # thread) is spared 90 % of the reads while nothing moves.
        self._state_poll_s = state_poll_s
        self._rest_state_poll_s = max(rest_state_poll_s, state_poll_s)
        self._active_until = 0.0
        self._max_lost = max_lost_frames
        self._reconnect_max_s = reconnect_max_s
        self._watchdog_s = watchdog_s
        # No frame back at all for this long is a pulled cable (an error): half the
        # watchdog, so that the user reads it before the drive has stopped, and a few
        # lost frames in a row (each ~10 ms of SOEM's waiting) are only counted.
        self._silent_limit_s = max(max_lost_frames * cycle_s, watchdog_s / 2)
        self.halt = threading.Event()
        """Set: the cycle thread shuts the slave down and ends."""
        self._connected = False
        self._paced_lost = 0  # the cycle process's lost exchanges counted so far
        # CoE values: last read or written, and what to write at every bring-up
        self._coe: dict[SdoObject, int] = {}
        self._stored: dict[SdoObject, int] = {}
        if settings is not None:
            for obj, value in codec.settings_writes(settings):
                if obj != codec.TIME_INFORMATION:  # manual: cannot be changed
                    self._stored[obj] = value
        self.handshakes = self._hs = Handshakes(
            cycle_s=cycle_s, queue=queue, reports=reports, coe=self._coe, counters=counters
        )
        self._revision: int | None = None
        # When the last frame the slave took was sent (see WATCHDOG_MARGIN_S).
        self._last_good = time.monotonic()
        # the last outputs encoded and inputs decoded: most cycles send the same
        # outputs, and at rest receive the same inputs, as the one before
        self._outputs_key: tuple[object, ...] | None = None
        self._outputs_bytes = b""
        self._inputs_raw = b""
        self._inputs_decoded = Inputs()
        # the flags of the last sample and what they were built from: they change
        # rarely, so consecutive samples share one (never mutated) dict
        self._flags_key: tuple[int, int, int, bool, bool, bool] | None = None
        self._flags: dict[str, bool] = {}

    @property
    def connected(self) -> bool:
        """In OP and exchanging (the thread's view; the link's state follows it)."""
        return self._connected

    # --- the cycle thread -------------------------------------------------------------------

    def _raise_priority(self) -> None:
        """Give the cycle thread a larger CPU share (nice ``CYCLE_THREAD_NICE``).

        The slave's watchdog (100 ms, the device default) is the safe stop if the host
        dies, and it trips just the same when the host is merely busy: a cycle thread
        that gets no CPU for 100 ms makes the drive drop Enable. A loaded host (other
        work on all cores) is the normal case on a laptop, so the thread asks the
        kernel for more weight. Only this thread; it sleeps between cycles, so it
        cannot starve the others. Needs CAP_SYS_NICE (or root), granted like
        CAP_NET_RAW for real hardware; without it the thread runs at normal priority
        and the counter ``watchdog_trips`` shows what that costs.
        """
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), CYCLE_THREAD_NICE)
        except (OSError, AttributeError) as exc:
            logger.info("%s: cycle thread at normal priority (%s)", self.id, exc)
        else:
            logger.info("%s: cycle thread at nice %d", self.id, CYCLE_THREAD_NICE)

    def _read_coe(self, slave: EthercatSlave, obj: SdoObject) -> int:
        value = codec.decode_sdo(obj, slave.sdo_read(obj.index, obj.subindex, obj.data_type.size))
        self._coe[obj] = value
        return value

    def _check_stall(self) -> None:
        """After a gap longer than the watchdog the slave has dropped its outputs."""
        gap_s = time.monotonic() - self._last_good
        if gap_s > self._watchdog_s - WATCHDOG_MARGIN_S:
            self._hs.drop_outputs(gap_s, self._watchdog_s)

    def _refresh_last_good(self, master: EthercatMaster) -> None:
        """With a paced master the slave's watchdog runs on the cycle process's
        exchanges: take the send time of its last good one (this thread may have been
        held up while that cycle went on)."""
        if isinstance(master, PacedMaster):
            last = master.last_good_t()
            if last is not None:
                self._last_good = max(self._last_good, last)

    def run(self, master: EthercatMaster) -> None:
        """The cycle thread: bring-up, cycles, drop-outs and bring-up again, until
        ``halt``; then the shutdown. Reports every fault; never raises."""
        connected_once = False
        told_priority = False
        tripped = False
        backoff_s = 0.25
        self._raise_priority()
        try:
            while not self.halt.is_set():
                try:
                    slave = self._bring_up(master)
                except _BringUpError as exc:
                    self._went_down(master, None, LinkDownError(f"link {self.id} is down: {exc}"))
                    state: LinkState = (
                        "error"
                        if exc.fatal or exc.no_answer or not connected_once
                        else "reconnecting"
                    )
                    self._reports.post_state(state, str(exc))
                    if self.halt.wait(backoff_s):
                        break
                    backoff_s = min(backoff_s * 2, self._reconnect_max_s)
                    continue
                if connected_once:
                    self._reports.post_event(
                        "warning",
                        f"{self.id}: slave {self._slave_pos} is back in OP"
                        + (" after its watchdog trip" if tripped else "")
                        + "; Enable is off - press Enable to continue",
                        axis=False,
                    )
                tripped = False
                connected_once = True
                backoff_s = 0.25
                if isinstance(master, PacedMaster) and not told_priority:
                    told_priority = True
                    if master.priority_text:
                        level: EventLevel = "info" if master.priority_granted else "warning"
                        self._reports.post_event(
                            level, f"{self.id}: {master.priority_text}", axis=False
                        )
                revision = f"rev 0x{self._revision or 0:08X}"
                self._reports.post_state(
                    "connected",
                    f"EP7047-1032 {revision} in OP on {self._ifname}, slave {self._slave_pos}, "
                    f"{self._cycle_s * 1000:g} ms cycle",
                )
                self._reports.post_health("ok", f"EP7047-1032 {revision}")
                try:
                    try:
                        self._cyclic(master, slave)
                    except (EthercatError, OSError) as exc:  # e.g. the NIC went away
                        raise _DropOutError(f"EtherCAT failed on {self._ifname}: {exc}") from exc
                except _DropOutError as exc:
                    self._counters.errors += 1
                    tripped = exc.watchdog
                    self._went_down(master, slave, LinkDownError(f"link {self.id} is down: {exc}"))
                    self._reports.post_health("offline", str(exc))
                    self._reports.post_state(exc.state, str(exc))
                    self._reports.post_event("error", f"{self.id}: {exc}", axis=False)
                    if self.halt.wait(0.25):
                        break
                    continue
                self._shutdown(master, slave)
                break
        except Exception as exc:  # a bug here must be visible, and the link must say so
            logger.exception("EtherCAT cycle thread of %s failed", self.id)
            self._went_down(master, None, LinkDownError(f"link {self.id} failed: {exc}"))
            self._reports.post_state("error", f"internal error in the cycle thread: {exc!r}")
            self._reports.post_health("offline", "internal error in the EtherCAT driver")
        finally:
            self._reports.flush_samples()
            self._connected = False
            self._close_quietly(master)
            if isinstance(master, PacedMaster):
                with contextlib.suppress(Exception):
                    master.shutdown()

    def _went_down(
        self, master: EthercatMaster, slave: EthercatSlave | None, error: Exception
    ) -> None:
        """The link is down: fail every request, acknowledge errors, close the master."""
        self._connected = False
        self._fail_all(error)
        if slave is not None:
            self._acknowledge(master, slave)
        self._close_quietly(master)

    def _close_quietly(self, master: EthercatMaster) -> None:
        with contextlib.suppress(Exception):
            master.close()

    def _fail_all(self, error: Exception) -> None:
        cs = self._hs.state
        for request in (cs.pending, cs.sdo_job, *cs.after_exchange):
            if request is not None:
                self._reports.reject(request, error)
        cs.pending = cs.sdo_job = None
        cs.after_exchange.clear()
        for request in self._queue.take_all():
            self._reports.reject(request, error)

    def _acknowledge(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        """Acknowledge the slave's error indication (the bring-up acknowledges again)."""
        with contextlib.suppress(Exception):
            master.read_state()
            state = slave.state
            if state & STATE_ERROR:
                slave.state = (state & 0x0F) | STATE_ACK
                slave.write_state()

    # --- bring-up -----------------------------------------------------------------------

    def _bring_up(self, master: EthercatMaster) -> EthercatSlave:
        """Open, enumerate, check identity, assign PDOs, write settings, SAFE-OP, OP."""
        # Whatever was queued while the link was down must not run after it returns.
        self._fail_all(LinkDownError(f"link {self.id} was down: nothing was sent"))
        try:
            return self._bring_up_steps(master)
        except EthercatUnavailableError as exc:
            raise _BringUpError(str(exc), fatal=True) from exc
        except (EthercatError, OSError) as exc:
            raise _BringUpError(f"bring-up failed on {self._ifname}: {exc}") from exc
        except CodecError as exc:
            raise _BringUpError(f"bring-up read a malformed CoE value: {exc}") from exc

    def _bring_up_steps(self, master: EthercatMaster) -> EthercatSlave:
        where = f"{self._ifname}, slave {self._slave_pos}"
        master.open(self._ifname)
        found = master.config_init()
        if found <= 0:
            raise _BringUpError(
                f"no EtherCAT slave answers on {self._ifname}: check the cable into the "
                "box's X1 IN port, the link/activity LEDs at both ends and the 24 V supply",
                no_answer=True,
            )
        if self._slave_pos > len(master.slaves):
            raise _BringUpError(
                f"slave {self._slave_pos} requested but only {len(master.slaves)} found on "
                f"{self._ifname}: check ?slave= in the link spec",
                fatal=True,
            )
        slave = master.slaves[self._slave_pos - 1]
        if (slave.man, slave.id) != (codec.VENDOR_ID, codec.PRODUCT_CODE):
            raise _BringUpError(
                f"slave {self._slave_pos} on {self._ifname} is not an EP7047-1032: it is "
                f"{slave.name or 'unnamed'} (vendor 0x{slave.man:08X}, product "
                f"0x{slave.id:08X}, revision 0x{slave.rev:08X}); expected vendor "
                f"0x{codec.VENDOR_ID:08X} product 0x{codec.PRODUCT_CODE:08X}. Check "
                "?slave= in the link spec",
                fatal=True,
            )
        self._revision = slave.rev
        state = slave.state_check(PREOP_STATE, 50_000)
        if state != PREOP_STATE:
            raise _BringUpError(
                f"slave did not reach PRE-OP ({where}): {state_name(state)}, "
                f"{al_status_text(slave.al_status)}"
            )
        try:
            self._assign_pdos(slave)
            self._write_stored(slave)
            values = self._read_parameters(slave)
            self._check_speed_range(slave)
        except EthercatSdoError as exc:
            raise _BringUpError(f"CoE set-up refused ({where}): {exc}") from exc
        except EthercatMailboxError as exc:
            raise _BringUpError(f"CoE set-up got no answer ({where}): {exc}") from exc
        try:
            master.config_map()
        except EthercatError as exc:
            raise _BringUpError(f"mapping the process data failed ({where}): {exc}") from exc
        out_size, in_size = len(slave.output), len(slave.input)
        if (out_size, in_size) != (codec.OUTPUTS_SIZE, codec.INPUTS_SIZE):
            raise _BringUpError(
                f"the process image is {out_size}/{in_size} bytes, expected "
                f"{codec.OUTPUTS_SIZE}/{codec.INPUTS_SIZE} for the positioning interface: "
                "the PDO assignment was not taken",
                fatal=True,
            )
        state = master.state_check(SAFEOP_STATE, 50_000)
        if state != SAFEOP_STATE:
            master.read_state()
            raise _BringUpError(
                f"slave did not reach SAFE-OP ({where}): {state_name(slave.state)}, "
                f"{al_status_text(slave.al_status)}"
            )
        # Valid (all-zero: Enable off) outputs before OP, then request OP.
        self._hs.reset()
        slave.output = codec.encode_outputs(self._hs.state.outputs())
        master.send_processdata()
        master.receive_processdata(self._receive_timeout_us())
        master.state = OP_STATE
        master.write_state()
        for _ in range(40):
            slave.output = codec.encode_outputs(self._hs.state.outputs())
            master.send_processdata()
            master.receive_processdata(self._receive_timeout_us())
            if master.state_check(OP_STATE, 50_000) == OP_STATE:
                break
            if self.halt.is_set():
                raise _BringUpError("shutting down")
        else:
            master.read_state()
            raise _BringUpError(
                f"slave did not reach OP ({where}): {state_name(slave.state)}, "
                f"{al_status_text(slave.al_status)}"
            )
        self._hs.state.inputs = codec.decode_inputs(slave.input)
        self._hs.state.next_state_poll = self._clock()
        self._last_good = time.monotonic()
        self._connected = True
        self._reports.post_params(values, "read")
        return slave

    def _receive_timeout_us(self) -> int:
        return min(2000, int(self._cycle_s * 1e6))

    def _assign_pdos(self, slave: EthercatSlave) -> None:
        """ "Positioning interface": 0x1C12/0x1C13 in PRE-OP (sub 0 = 0, entries, count)."""
        for index, pdos in (
            (0x1C12, codec.RXPDO_ASSIGNMENT),
            (0x1C13, codec.TXPDO_ASSIGNMENT),
        ):
            slave.sdo_write(index, 0, bytes([0]))
            for subindex, pdo in enumerate(pdos, start=1):
                slave.sdo_write(index, subindex, struct.pack("<H", pdo))
            slave.sdo_write(index, 0, bytes([len(pdos)]))
            count = slave.sdo_read(index, 0, 1)[0]
            found = tuple(
                struct.unpack("<H", slave.sdo_read(index, s, 2))[0] for s in range(1, count + 1)
            )
            if found != pdos:
                raise _BringUpError(
                    f"PDO assignment 0x{index:04X} reads {[hex(p) for p in found]} after "
                    f"writing {[hex(p) for p in pdos]}",
                    fatal=True,
                )

    def _write_stored(self, slave: EthercatSlave) -> None:
        for obj, value in self._stored.items():
            slave.sdo_write(obj.index, obj.subindex, codec.encode_sdo(obj, value))

    def _read_parameters(self, slave: EthercatSlave) -> dict[str, int]:
        values = {name: self._read_coe(slave, obj) for name, obj in PARAMETER_SDO.items()}
        values[INVERSION_PARAMETER] = sum(
            self._read_coe(slave, obj) << bit for bit, obj in INVERSION_BITS.items()
        )
        return values

    def _check_speed_range(self, slave: EthercatSlave) -> None:
        code = self._read_coe(slave, codec.SPEED_RANGE)
        steps_s = codec.SPEED_RANGE_STEPS_S.get(code)
        if steps_s != self._speed_range:
            self._reports.post_event(
                "warning",
                f"the drive's speed range 0x8012:05 is code {code} "
                f"({steps_s or 'unknown'} full steps/s) but the link is configured for "
                f"{self._speed_range} steps/s: velocities in steps/s are shown wrong - set "
                "speed_range on the link",
            )

    # --- cyclic operation ---------------------------------------------------------------

    def _cyclic(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        period = self._cycle_s
        deadline = time.monotonic()
        if isinstance(master, PacedMaster):
            # The cycle process keeps the period; receive_processdata waits for it. Its
            # cycles in SAFE-OP (working counter 1) are no lost frames: count from here.
            master.last_good_t()
            self._paced_lost = master.cycle_lost
            while not self.halt.is_set():
                self._one_cycle(master, slave)
            return
        while not self.halt.is_set():
            self._one_cycle(master, slave)
            deadline += period
            delay = deadline - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -period:
                self._counters.overruns += 1
                deadline = time.monotonic()

    def _exchange(self, master: EthercatMaster, slave: EthercatSlave) -> bool:
        cs = self._hs.state
        # Checked again here, after this cycle's other steps (an SDO, a request) and right
        # before the frame leaves: the slave's watchdog runs between frames, whatever
        # held this thread up.
        sent_t = time.monotonic()
        if sent_t - self._last_good > self._watchdog_s - WATCHDOG_MARGIN_S:
            self._refresh_last_good(master)
            self._check_stall()
        key = (
            cs.enable, cs.reset, cs.emergency, cs.execute, cs.target, cs.velocity_bp,
            cs.start_type, cs.acceleration_ms, cs.deceleration_ms,
        )  # fmt: skip
        if key != self._outputs_key:  # the fields _CycleState.outputs() encodes
            self._outputs_key = key
            self._outputs_bytes = codec.encode_outputs(cs.outputs())
        slave.output = self._outputs_bytes
        master.send_processdata()
        wkc = master.receive_processdata(self._receive_timeout_us())
        paced = False
        if isinstance(master, PacedMaster):
            paced = True
            # The cycle process sees every exchange, this thread only some: count its.
            lost = master.cycle_lost
            if lost > self._paced_lost:
                self._counters.errors += lost - self._paced_lost
                self._counters.lost_frames += lost - self._paced_lost
            self._paced_lost = lost
        if wkc == master.expected_wkc:
            self._hs.state.lost_in_row = self._hs.state.silent_in_row = 0
            # The send time, not now: the slave restarted its watchdog when the frame
            # arrived, and this thread may have run again only long after the reply.
            self._last_good = sent_t
            self._refresh_last_good(master)
            return True
        if not paced:
            self._counters.errors += 1
            self._counters.lost_frames += 1
        cs = self._hs.state
        cs.lost_in_row += 1
        if wkc < 0:
            # No frame came back at all: nothing on the wire answers, so no state can be
            # read either (reading it would only wait for more timeouts).
            # Counted in time, not cycles: SOEM waits ~10 ms for a frame that never
            # comes (however short the timeout), so a silent cycle lasts that long.
            if cs.silent_in_row == 0:
                cs.silent_since = sent_t
            cs.silent_in_row += 1
            if paced:
                # The cycle process saw every exchange: silence is the time since its
                # last good one, not between the few cycles this thread happened to see
                # (two isolated losses around a stall of this thread are no pulled cable).
                silent_s = time.monotonic() - self._last_good
            else:
                silent_s = time.monotonic() - cs.silent_since
            if cs.silent_in_row >= 2 and silent_s >= self._silent_limit_s:
                raise _DropOutError(
                    f"no EtherCAT frame comes back on {self._ifname} (for "
                    f"{silent_s * 1000:.0f} ms): the cable is pulled, the link is down or the "
                    "box has no power - the drive's watchdog stops the motor; retrying",
                    state="error",
                )
            return False
        cs.silent_in_row = 0
        master.read_state()
        state = slave.state
        if state != OP_STATE:
            if slave.al_status == AL_WATCHDOG:
                raise _DropOutError(
                    watchdog=True,
                    message=f"{watchdog_trip_text(self._ifname, self._slave_pos)} (now "
                    f"{state_name(state)})",
                )
            raise _DropOutError(
                f"slave {self._slave_pos} on {self._ifname} left OP: now {state_name(state)}, "
                f"{al_status_text(slave.al_status)}"
            )
        if self._hs.state.lost_in_row >= self._max_lost:
            raise _DropOutError(
                f"no process data from slave {self._slave_pos} on {self._ifname} for "
                f"{self._hs.state.lost_in_row} cycles (working counter {wkc}, expected "
                f"{master.expected_wkc}): cable or power?"
            )
        return False

    def _one_cycle(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        self._reports.begin_cycle()
        try:
            self._cycle_steps(master, slave)
        finally:
            self._reports.end_cycle()

    def _cycle_steps(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        # Each step is called only when it has work (the same tests it starts with): at
        # 500 cycles/s the calls of idle steps were a good part of the thread's Python
        # time, and every microsecond here is one the event loop waits for the GIL.
        cs = self._hs.state
        queue = self._queue
        now = self._clock()
        if time.monotonic() - self._last_good > self._watchdog_s - WATCHDOG_MARGIN_S:
            self._refresh_last_good(master)
            self._check_stall()
        # A racy peek at the deque (no lock): a request appended meanwhile is taken next
        # cycle, and take_urgent reads it under the lock.
        if queue.urgent:
            self._hs.take_urgent(now)
        if cs.pending is not None or cs.exec_state is _Exec.ARMING:
            self._hs.before_exchange(now)  # what an earlier cycle prepared (Execute after ARMING)
        if cs.pending is None and cs.sdo_job is None and queue.normal:
            self._hs.take_normal(now)
        if not self._exchange(master, slave):
            return  # stale inputs: no sample, nothing decided on them
        now = self._clock()
        previous = cs.inputs
        raw = slave.input
        if raw != self._inputs_raw:  # Inputs is immutable: the same bytes, the same object
            self._inputs_decoded = codec.decode_inputs(raw)  # may raise: then not cached
            self._inputs_raw = raw
        cs.inputs = inputs = self._inputs_decoded
        if cs.after_exchange:
            for request in cs.after_exchange:
                self._reports.resolve(request, "sent")
            cs.after_exchange.clear()
        if (int(inputs.pos_status) & _POS_WARNING or int(cs.diag)) and self._hs.diag_due(
            previous, inputs, now
        ):
            try:
                word = self._read_coe(slave, codec.POS_STATUS_WORD)
            except (EthercatError, CodecError):
                self._counters.errors += 1
            else:
                self._hs.take_diag(word, now)
        if cs.stop_phase is not _StopPhase.NONE:
            self._hs.advance_stop(inputs, now)
        if cs.exec_state is _Exec.RUNNING or cs.exec_state is _Exec.HALTING:
            self._hs.advance_exec(inputs, now)
        if cs.pending is not None:
            self._hs.advance_pending(inputs, now)
        if cs.sdo_job is not None or now >= cs.next_state_poll:
            fresh_state = self._sdo_slot(slave, now)
        else:
            fresh_state = None
        self._emit(inputs, now, fresh_state)

    # --- SDO slot and sample ------------------------------------------------------------

    def _sdo_slot(self, slave: EthercatSlave, now: float) -> int | None:
        """Run the user's SDO transfer, else sample the drive state when it is due."""
        cs = self._hs.state
        job = cs.sdo_job
        if job is not None:
            cs.sdo_job = None
            self._run_sdo(slave, job)
            return None
        if now < cs.next_state_poll:
            return None
        active = (
            cs.execute
            or cs.inputs.busy
            or cs.stop_phase is not _StopPhase.NONE
            or now < self._active_until
        )
        cs.next_state_poll = now + (self._state_poll_s if active else self._rest_state_poll_s)
        try:
            cs.drive_state = self._read_coe(slave, codec.DRIVE_STATE)
        except (EthercatError, CodecError):
            self._counters.errors += 1
            return None
        return cs.drive_state

    def _run_sdo(self, slave: EthercatSlave, job: _Request) -> None:
        obj = job.obj
        assert obj is not None
        where = f"0x{obj.index:04X}:{obj.subindex:02X} {obj.name}"
        try:
            if job.kind is _Kind.SDO_READ:
                self._reports.resolve(job, self._read_coe(slave, obj))
            else:
                data = codec.encode_sdo(obj, job.value)
                slave.sdo_write(obj.index, obj.subindex, data)
                self._coe[obj] = job.value
                self._stored[obj] = job.value
                self._reports.resolve(job, None)
        except EthercatSdoError as exc:
            self._counters.errors += 1
            message = f"{where}: the drive refused it: {exc}"
            if job.kind is _Kind.SDO_WRITE and exc.abort_code in VALUE_ABORT_CODES:
                error: DeviceRefusedError = SdoValueRefusedError(
                    message, exc.abort_code, f"SDO abort 0x{exc.abort_code:08X} ({exc.desc})"
                )
            else:
                error = DeviceRefusedError(message)
            self._reports.reject(job, error)
        except EthercatMailboxError as exc:
            self._counters.errors += 1
            self._reports.reject(job, DeviceTimeoutError(f"{where}: no answer: {exc}"))
        except CodecError as exc:
            self._counters.errors += 1
            self._reports.reject(job, ProtocolError(f"{where}: {exc}"))

    def _emit(self, inputs: Inputs, now: float, drive_state: int | None) -> None:
        cs = self._hs.state
        velocity = inputs.actual_velocity_bp * self._speed_range / codec.SPEED_RANGE_FULL_SCALE_BP
        channels: dict[str, float | None] = {
            "position": float(inputs.actual_position_counts),
            "target": cs.target_estimate,
            "velocity": velocity,
            "drive_time": float(inputs.actual_drive_time_ms),
            "drive_state": float(drive_state) if drive_state is not None else None,
        }
        # Without the TxPDO toggle: it flips with the drive's own cycle, is no flag, and
        # would count as a change (a flags rebuild, the drive state at the fast rate).
        pos, stm, diag = int(inputs.pos_status), int(inputs.stm_status) & _STM_SHOWN, int(cs.diag)
        key = (pos, stm, diag, cs.enable, cs.execute, cs.emergency)
        if key != self._flags_key:  # rare: most cycles repeat the last flags
            # Something changed: the drive state is read at the fast rate again, now.
            self._active_until = now + STATE_ACTIVE_S
            cs.next_state_poll = min(cs.next_state_poll, now + self._state_poll_s)
            flags = {name: pos & bit != 0 for name, bit in _POS_BITS}
            for name, bit in _STM_BITS:
                flags[name] = stm & bit != 0
            for name, bit in _DIAG_BITS:
                flags[name] = diag & bit != 0
            flags["enable_out"] = cs.enable
            flags["execute_out"] = cs.execute
            flags["emergency_stop_out"] = cs.emergency
            self._flags_key, self._flags = key, flags
        self._reports.post_sample(Sample(now, channels, self._flags))

    # --- shutdown -------------------------------------------------------------------------

    def _shutdown(self, master: EthercatMaster, slave: EthercatSlave) -> None:
        """Server stops: ramp a moving axis down, Enable off, slave to INIT."""
        cs = self._hs.state
        self._fail_all(LinkDownError(f"link {self.id} is shutting down"))
        with contextlib.suppress(Exception):
            if cs.enable and (cs.inputs.busy or cs.inputs.actual_velocity_bp):
                cs.execute = False
                cs.emergency = True
                end = time.monotonic() + 1.0
                while time.monotonic() < end:
                    if self._exchange(master, slave):
                        cs.inputs = codec.decode_inputs(slave.input)
                        if not cs.inputs.busy and cs.inputs.actual_velocity_bp == 0:
                            break
                    time.sleep(self._cycle_s)
            self._hs.reset()
            for _ in range(2):
                self._exchange(master, slave)
                time.sleep(self._cycle_s)
            master.state = INIT_STATE
            master.write_state()
