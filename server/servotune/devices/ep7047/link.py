"""Beckhoff EP7047-1032 EtherCAT driver: one slave, its positioning interface, one axis.

EtherCAT is not a byte channel, so this link implements ``link.base.Link`` directly
(not ``link.engine.LinkEngine``) but keeps its rules: one owner, STOP ahead of
everything, jobs refused while the link is down, state through the ``DriverSink``.

The library seam
    The driver talks to an EtherCAT *master* through :class:`EthercatMaster`, a small
    protocol with pysoem's own names (``open``, ``config_init``, ``slaves``,
    ``config_map``, ``send_processdata``, ``receive_processdata``, ``read_state``,
    ``write_state``, ``state_check``, ``state``, ``expected_wkc``, ``close``; per slave
    ``man``/``id``/``rev``, ``sdo_read``/``sdo_write``, ``input``/``output``, ``state``,
    ``al_status``, ``write_state``, ``state_check``). :class:`PysoemMaster` is the thin
    adapter over a real ``pysoem.Master`` (``pip install 'servotune[ethercat]'``);
    ``servotune.devices.ep7047.sim.slave.SimulatedEthercatMaster`` is the fake used by the tests
    and the demo.

The owner: one cycle thread
    Process data must flow every 1..4 ms (default 2 ms) whatever the event loop does, so
    one thread per link owns the master: bring-up, the cyclic exchange (``time.sleep``
    to an absolute deadline, so the period does not drift; more than one period late it
    re-anchors and counts an overrun), and every SDO transfer - between two exchanges,
    never concurrently with them. The event loop only submits requests to thread-safe
    queues and gets results, samples and state changes back through
    ``loop.call_soon_threadsafe``. Every cycle's sample is delivered, in batches of
    ``SAMPLE_BATCH_S`` (one loop wake-up per batch, not per cycle).

Parts (this module re-exports their public names): ``transports.ethercat`` the library
seam (protocols, errors, state values, pysoem adapter); ``devices.ep7047.requests`` the
requests, their queue, the cycle state and counters (data); here ``Ep7047Link``, which
*has* a ``devices.ep7047.bridge.EventLoopBridge`` (status, the posts from the thread to the
loop, sample batches) and a ``devices.ep7047.cycle.Cycle`` (bring-up, exchange, SDO
slots, samples, shutdown; it reports through ``CycleReports``, which the bridge
implements), which *has* the ``devices.ep7047.handshakes.Handshakes`` (the command
handshakes, sans-IO); ``devices.ep7047.axis`` ``Ep7047Axis`` (parameters, commands,
console, bench planner; it talks to the link through ``Ep7047AxisLink``).

Each cycle: (1) urgent requests (STOP, emergency stop, Halt) go into the outputs of this
very exchange; (2) the next user request, one at a time (an SDO transfer, or a command
that watches the inputs until the drive has taken it); (3) exchange and working-counter
check; (4) the handshakes: Enable until STM Ready, Reset pulsed, Execute held until Busy
has risen and fallen; (5) one SDO (the user's, or a sample of the drive state
0x9020:03); (6) the sample.

Safety: the SyncManager watchdog of the slave is left on. If servotune (or its host)
dies, no process data arrives and the slave drops its outputs (Enable off) after the
watchdog time (100 ms by default). If the cycle thread itself stalls that long, the
driver drops Enable and Execute too, so they are not re-asserted silently when the
process data resumes. After a drop out of OP the bring-up runs again and the outputs
start from zero: the axis never resumes a move or Enable by itself.

Decisions (also in docs/ep7047-driver.md):

* STOP = Emergency stop (emergency deceleration) and Execute low on the next cycle,
  queued user commands are discarded (a move queued behind a STOP must never run),
  then Enable off once the drive reports standstill (or after the emergency
  deceleration time + 0.5 s). "Emergency stop" keeps Enable (holding torque) and
  releases the bit at standstill; "Halt" only drops Execute (the drive ramps down with
  the move's deceleration - the normal end of an ENDLESS move).
* A plain start writes target, velocity, start type and ramps one cycle before raising
  Execute; Execute stays high until Busy has risen and fallen (dropping it earlier
  would abort the move), then drops. A command that ends within one 250 us drive cycle
  may never show Busy: when Busy has not risen within max(10 cycles, 25 ms), Execute is
  dropped and the flags decide (Error -> refused). ``execute_move`` returns when the
  drive has taken the move (Busy seen for two cycles) or answered it.
* A _CHANGE start type is written with Execute still high; the driver watches the
  diagnosis (0x9020:01) for a new "Command rejected" for max(10 cycles, 25 ms).
* Refused by the server (409) because the drive would refuse it: a start while not
  enabled, during STOP, or while a move runs (use a _CHANGE type); a _CHANGE type with
  Execute low; ADDITIVE_CHANGE during ENDLESS; modulo starts with modulo factor 0, a
  negative target, or a SHORT target >= the modulo factor; Reset while Busy;
  SET_CALIBRATION_AUTO through the process data (it is meant as default start type).
  Errors the drive reports itself (Error, Command rejected) come back as 409 with the
  decoded diagnosis.
* Working counter: a cycle whose working counter is not ``expected_wkc`` is lost (no
  sample, counted in ``errors``); then the slave's AL state is read: out of OP is a
  drop-out at once, otherwise 10 lost cycles in a row are.
* Parameters are written by SDO and read back; the written values are kept and written
  again at every later bring-up (after a drop-out or a power cycle of the box).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from servotune.descriptor import DeviceDescriptor
from servotune.devices.ep7047.axis import Ep7047Axis
from servotune.devices.ep7047.bridge import EventLoopBridge
from servotune.devices.ep7047.codec import PosSettings, SdoObject
from servotune.devices.ep7047.cycle import Cycle
from servotune.devices.ep7047.descriptor import ep7047_descriptor
from servotune.devices.ep7047.requests import (
    DEFAULT_COUNTS_PER_REV,
    DEFAULT_SPEED_RANGE_STEPS_S,
    WATCHDOG_S,
    CycleCounters,
    RequestQueue,
    _Kind,
    _Request,
    diag_text,
)
from servotune.link.base import (
    AxisDriver,
    DriverError,
    DriverSink,
    LinkDownError,
)
from servotune.schema import LinkState
from servotune.transports.ethercat import (
    BOOT_STATE,
    INIT_STATE,
    NONE_STATE,
    OP_STATE,
    PREOP_STATE,
    PYSOEM_MISSING,
    SAFEOP_STATE,
    STATE_ACK,
    STATE_ERROR,
    EthercatError,
    EthercatMailboxError,
    EthercatMaster,
    EthercatSdoError,
    EthercatSlave,
    EthercatUnavailableError,
    PysoemMaster,
    raw_socket_problem,
    state_name,
)
from servotune.transports.ethercat_cycle import CycleProcessMaster

logger = logging.getLogger(__name__)


class Ep7047Link:
    """One EtherCAT network interface with one EP7047-1032 slave; see the module docstring.

    It has an ``EventLoopBridge`` (status, samples and results on the event loop) and a
    ``Cycle`` (the thread that owns the master, with the command handshakes); requests
    go to the cycle through a ``RequestQueue``.
    """

    device = "ep7047"

    def __init__(
        self,
        link_id: str,
        ifname: str,
        slave: int,
        sink: DriverSink,
        master_factory: Callable[[], EthercatMaster],
        *,
        cycle_s: float = 0.002,
        speed_range_steps_s: int = DEFAULT_SPEED_RANGE_STEPS_S,
        counts_per_rev: int = DEFAULT_COUNTS_PER_REV,
        settings: PosSettings | None = None,
        name: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        state_poll_s: float = 0.01,
        rest_state_poll_s: float = 0.1,
        max_lost_frames: int = 10,
        reconnect_max_s: float = 5.0,
        watchdog_s: float = WATCHDOG_S,
    ) -> None:
        if not 0.001 <= cycle_s <= 0.004:
            raise ValueError(f"cycle_s must be 0.001..0.004 s, got {cycle_s}")
        if slave < 1:
            raise ValueError(f"slave positions start at 1, got {slave}")
        self._link_id = link_id
        self._ifname = ifname
        self._slave_pos = slave
        self._sink = sink
        self._master_factory = master_factory
        self._cycle_s = cycle_s
        self._counts_per_rev = counts_per_rev
        self._clock = clock
        self._reconnect_max_s = reconnect_max_s
        self._descriptor = ep7047_descriptor(speed_range_steps_s, counts_per_rev)
        self._axis_name = name or f"EP7047-1032 #{slave}"
        self._counters = CycleCounters()
        self._queue = RequestQueue()
        self.bridge = EventLoopBridge(
            link_id,
            self.axis_id,
            sink,
            self._counters,
            wire_limit_hz=self.wire_limit_hz(),
            clock=clock,
        )
        self.cycle = Cycle(
            link_id,
            ifname,
            slave,
            queue=self._queue,
            reports=self.bridge,
            counters=self._counters,
            cycle_s=cycle_s,
            speed_range_steps_s=speed_range_steps_s,
            settings=settings,
            clock=clock,
            state_poll_s=state_poll_s,
            rest_state_poll_s=rest_state_poll_s,
            max_lost_frames=max_lost_frames,
            reconnect_max_s=reconnect_max_s,
            watchdog_s=watchdog_s,
        )

    # --- Link protocol ------------------------------------------------------------------

    @property
    def id(self) -> str:
        return self._link_id

    @property
    def path(self) -> str:
        return f"{self._ifname} slave {self._slave_pos}"

    @property
    def baud(self) -> int:
        return 0  # not a serial line

    @property
    def state(self) -> LinkState:
        return self.bridge.state

    @property
    def message(self) -> str:
        """What the link's state means now (the status message)."""
        return self.bridge.message

    @property
    def errors(self) -> int:
        """Lost cycles (bad working counter) and failed SDO transfers since start."""
        return self._counters.errors

    @property
    def descriptor(self) -> DeviceDescriptor:
        return self._descriptor

    @property
    def axis_id(self) -> str:
        return f"{self._link_id}-{self._slave_pos}"

    @property
    def cycle_s(self) -> float:
        return self._cycle_s

    def wire_limit_hz(self) -> float:
        return 1 / self._cycle_s

    def achieved_rate_hz(self) -> float:
        """Samples/s over the last 2 s, falling to 0 within 2 s when the cycles stop."""
        return self.bridge.achieved_rate_hz()

    @property
    def counters(self) -> dict[str, int]:
        """Lost frames (bad working counter), cycle overruns (a cycle thread more than one
        period late), watchdog trips (more than ``watchdog_s`` without good process data:
        the drive dropped its outputs), restarts of the cycle thread after an internal
        error."""
        counters = self._counters
        return {
            "lost_frames": counters.lost_frames,
            "overruns": counters.overruns,
            "watchdog_trips": counters.watchdog_trips,
            "restarts": counters.restarts,
        }

    @functools.cached_property
    def _axis(self) -> Ep7047Axis:
        return Ep7047Axis(self, self._axis_name)

    @property
    def axes(self) -> list[AxisDriver]:
        return [self._axis]

    async def _create_master(self) -> EthercatMaster:
        while True:
            try:
                return self._master_factory()
            except EthercatUnavailableError as exc:
                self.bridge.set_state("error", str(exc))
            except Exception as exc:
                logger.exception("creating the EtherCAT master of %s failed", self.id)
                self.bridge.set_state("error", f"cannot create the EtherCAT master: {exc!r}")
            await asyncio.sleep(self._reconnect_max_s)

    async def run(self) -> None:
        """Create the master, run the cycle thread, publish status; never raises for faults.

        Supervised: a cycle thread that ends without being asked to (an internal error,
        which it logged and reported as ``error``) is replaced by a new one on a new
        master with backoff (0.25 s doubling to ``reconnect_max_s``), exactly like a
        drop-out; the axis never resumes Enable or a move by itself (the bring-up
        starts from zero outputs).
        """
        bridge, cycle = self.bridge, self.cycle
        bridge.attach(asyncio.get_running_loop())
        cycle.halt.clear()
        backoff_s = 0.25
        thread: threading.Thread | None = None
        try:
            while True:
                master = await self._create_master()
                cycle.handshakes.reset()
                thread = threading.Thread(
                    target=cycle.run,
                    args=(master,),
                    name=f"ep7047-cycle-{self.id}",
                    daemon=True,
                )
                thread.start()
                started = self._clock()
                last_status = started
                while thread.is_alive():
                    await asyncio.sleep(0.1)
                    if self._clock() - last_status >= 1.0:
                        last_status = self._clock()
                        bridge.publish_status()
                thread = None
                self._counters.restarts += 1
                if self._clock() - started > 30.0:
                    backoff_s = 0.25
                self._fail_queued(LinkDownError(f"link {self.id} is restarting: nothing was sent"))
                reason = bridge.message or "the cycle thread ended"
                bridge.set_state("error", f"{reason}; restarting in {backoff_s:g} s")
                await asyncio.sleep(backoff_s)
                backoff_s = min(backoff_s * 2, self._reconnect_max_s)
        finally:
            cycle.halt.set()
            self._fail_queued(LinkDownError(f"link {self.id} is shutting down"))
            if thread is not None:
                await asyncio.to_thread(thread.join, 10.0)

    def _fail_queued(self, error: Exception) -> None:
        self.bridge.fail(self._queue.take_all(), error)

    # --- requests (event loop side) -----------------------------------------------------

    async def submit(self, request: _Request) -> Any:
        """Queue ``request`` for the cycle thread and wait for its result."""
        state = self.bridge.state
        if not self.bridge.attached or state != "connected" or not self.cycle.connected:
            request.future.cancel()
            raise LinkDownError(f"link {self.id} is {state}: nothing was sent")
        self._queue.put(request)
        return await request.future

    def new_request(self, kind: _Kind, **values: Any) -> _Request:
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        return _Request(kind, future, **values)

    async def sdo_read(self, obj: SdoObject) -> int:
        value: int = await self.submit(self.new_request(_Kind.SDO_READ, obj=obj))
        return value

    async def sdo_write(self, obj: SdoObject, value: int) -> None:
        await self.submit(self.new_request(_Kind.SDO_WRITE, obj=obj, value=value))

    # --- what the axis reads (Ep7047AxisLink) -------------------------------------------

    @property
    def slave_position(self) -> int:
        """The slave's position on its EtherCAT network (1: the first)."""
        return self._slave_pos

    @property
    def counts_per_rev(self) -> int:
        return self._counts_per_rev

    def report_params(self, values: Mapping[str, int], source: str) -> None:
        """Tell the hub the axis' parameter values (``DriverSink.on_params``)."""
        self._sink.on_params(self.axis_id, values, source)


def _real_master(cycle_s: float, cycle_process: bool) -> EthercatMaster:
    """pysoem on a NIC; in a cycle process unless ``cycle_process`` is False."""
    try:
        import pysoem  # noqa: F401 - checked here, so that the link says so at once
    except ImportError as exc:
        raise EthercatUnavailableError(PYSOEM_MISSING) from exc
    if not cycle_process:
        return PysoemMaster()
    return CycleProcessMaster(PysoemMaster, cycle_s=cycle_s, name="ec-cycle")


def build_ep7047_link(
    link_id: str,
    ifname: str,
    slave: int,
    sink: DriverSink,
    *,
    master: EthercatMaster | None = None,
    cycle_s: float = 0.002,
    speed_range_steps_s: int = DEFAULT_SPEED_RANGE_STEPS_S,
    counts_per_rev: int = DEFAULT_COUNTS_PER_REV,
    settings: PosSettings | None = None,
    name: str | None = None,
    watchdog_s: float = WATCHDOG_S,
    cycle_process: bool = True,
) -> Ep7047Link:
    """An EP7047-1032 link on ``ifname`` (slave position ``slave``, from 1).

    ``master`` None uses the real pysoem master (created when the link runs, so a missing
    pysoem shows as the link's error state, not as a crash), in a cycle process of its
    own (``transports.ethercat_cycle``; ``cycle_process=False``: in the driver's thread,
    for comparison). ``settings``, when given, are written over CoE at every bring-up;
    otherwise the drive's own values are read.
    ``watchdog_s`` is the slave's SyncManager watchdog time (the device default, 100 ms):
    a longer gap in the process data makes the driver drop Enable.
    """
    factory: Callable[[], EthercatMaster]
    if master is None:
        factory = functools.partial(_real_master, cycle_s, cycle_process)
    else:
        given = master

        def factory() -> EthercatMaster:
            return given

    return Ep7047Link(
        link_id,
        ifname,
        slave,
        sink,
        factory,
        cycle_s=cycle_s,
        speed_range_steps_s=speed_range_steps_s,
        counts_per_rev=counts_per_rev,
        settings=settings,
        name=name,
        watchdog_s=watchdog_s,
    )


__all__ = [
    "BOOT_STATE",
    "INIT_STATE",
    "NONE_STATE",
    "OP_STATE",
    "PREOP_STATE",
    "SAFEOP_STATE",
    "STATE_ACK",
    "STATE_ERROR",
    "DriverError",
    "Ep7047Axis",
    "Ep7047Link",
    "EthercatError",
    "EthercatMailboxError",
    "EthercatMaster",
    "EthercatSdoError",
    "EthercatSlave",
    "EthercatUnavailableError",
    "PysoemMaster",
    "build_ep7047_link",
    "diag_text",
    "raw_socket_problem",
    "state_name",
]
