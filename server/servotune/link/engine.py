"""The device-independent part of every link: owner task, job queues, reconnects.

A device's link *has* a ``LinkEngine`` and implements ``LinkSession``, the small
Protocol the engine calls back through: ``run_session`` (what happens on an open
channel: probe, then poll until the channel fails), ``link_down`` (mark every axis
offline) and the two rates of its status. The engine provides:

* ``run()``: open the channel through the injected ``Connector``, run the session,
  and on a lost port report it and reopen with backoff (0.25 s doubling to
  ``reconnect_max_s``) — the server never needs a restart. The session is
  *supervised*: any other exception out of it (a driver bug, a reply nobody
  foresaw) is logged with its traceback, the link goes to ``error`` with the
  message, the channel is closed and the link reconnects with the same backoff.
  Nothing but a cancellation ends ``run()``;
* a status ticker beside the session that publishes the link status every
  ``STATUS_PERIOD_S`` whatever the session does, so a stalled session shows its
  rate falling to 0 instead of a frozen value;
* ``counters``: what was retried, resynchronised or dropped (shown with the link
  status) — a slow host makes a few of these, which are counted, not alarmed;
* ``wire_busy``: the share of the last ``RATE_WINDOW_S`` the line carried the link's
  characters (the device reports each exchange's wire time with ``wire_used``):
  polls, commands and echoes alike, so it tells a link that keeps its wire full
  while it also carries commands from one that loses time between exchanges;
* ``submit(job, urgent=...)``: run a coroutine on the owner task with exclusive use of
  the line. ``take_job`` hands out urgent jobs (stops) before user jobs; the session
  calls it between two wire transactions, so a stop waits at most for the one
  transaction in flight, never for queued polls. Jobs are refused at once while the
  link is down: a motion command must never be replayed later;
* link state and status publishing through the ``DriverSink``;
* the silence rule: a device that answers none of the requests sent to it is not shown
  ``connected``. The device reports each request that got no answer
  (``unanswered_request``) and each valid answer (``answered``); once
  ``SILENT_REQUESTS`` requests in a row went unanswered over at least ``SILENT_S``,
  the link shows ``error`` ("no answer from the device for ...") with an error event,
  checked at each unanswered request and by the status ticker (a session blocked in
  a long wait). Counting requests, not wall time, keeps a stalled host from raising
  it: a host that did not run sent nothing and missed no answer. The next good poll
  shows ``connected`` again, as after any line error.
* the host's excuse (``host_stalled``): a timeout is no evidence against the device
  when the host itself held the answer back for longer than the request listened -
  the server's loop noticed the timeout late (``ByteChannel.take_timeout_late_s``), or
  the host's tty layer held a canary byte that long meanwhile (``TtyGauge``; by
  default a ``transports.tty_probe.TtyProbe`` runs beside the session: every link here
  is a serial line whose bytes pass that layer). Bounded by ``HOST_STALL_EXCUSE_S``
  (``TTY_STALL_EXCUSE_S`` on the canary's evidence) without an answer, so a cut line
  still shows on a host that stalls all the time.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable, Coroutine, Iterable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar, overload

from servotune.link.base import DeviceRefusedError, DriverSink, LinkDownError
from servotune.schema import LinkState
from servotune.transports.base import ByteChannel, Connector, LinkClosedError
from servotune.transports.tty_probe import TtyProbe

T = TypeVar("T")

logger = logging.getLogger(__name__)

STATUS_PERIOD_S = 1.0
RATE_WINDOW_S = 2.0
# Counters every link reports (``LinkStatus.counters``); a device may add its own.
#   retries: transactions sent again after a timeout, a bad echo or a noisy reply;
#   desyncs: replies that belonged to another request (late, or refused/unknown
#            although the request cannot be), after which the line was resynchronised;
#   dropped_bytes: unsolicited bytes read and dropped (late echoes, line noise);
#   restarts: sessions ended by an internal error and restarted.
COUNTER_NAMES = ("retries", "desyncs", "dropped_bytes", "restarts")
SILENT_REQUESTS = 3
SILENT_S = 1.0
# A host stall excuses timeouts for this long at most without an answer between: on a
# host stalled all the time every timeout is noticed late, and a cut cable must still
# show (``_host_stalled``). Longer than the host's stalls measured under a CPU hog
# (docs/simulator.md, "Under load"), short against the silence rule's message.
HOST_STALL_EXCUSE_S = 2.0
# The same bound where the host's tty layer was seen holding bytes back (the canary,
# ``TtyGauge``): that is direct evidence of the moment, and such stalls last longer than
# the loop's own (a pty byte held up to 3.0 s while the server's timers ran on time,
# load 10-22 on 2 cores: docs/simulator.md, "Under load"). A line cut then shows once
# the layer flows again, or after this long.
TTY_STALL_EXCUSE_S = 5.0
_SILENT_PREFIX = "no answer from the device for"


def recent_rate_hz(times: Iterable[float], now: float, window_s: float = RATE_WINDOW_S) -> float:
    """Samples per second over the last ``window_s`` before ``now``.

    The intervals between the samples in the window over the time they span, that
    span extended to *now* as soon as the newest sample is older than one mean
    interval: a link that stops delivering shows its rate falling within one
    sample interval, and to 0 within ``window_s``, instead of keeping the rate of
    its last burst. Counting always to *now* would read a steady link low by the time
    since its newest sample: up to one interval per window, 2.8 % on average for the
    Z1100's ~11 Hz and 14 % for a 2 Hz link (tests/unit/link/test_rate.py).
    """
    recent = [t for t in times if 0.0 <= now - t <= window_s]
    if len(recent) < 2:
        return 0.0
    intervals = len(recent) - 1
    span_s = recent[-1] - recent[0]
    span_s = max(span_s, now - recent[0] - span_s / intervals)
    return intervals / span_s if span_s > 0 else 0.0


@dataclass(slots=True)
class Job:
    """A submitted coroutine, its submitter's future, and what it may move (``submit``)."""

    run: Callable[[], Awaitable[object]]
    future: asyncio.Future[object]
    axis: int | None = None
    motion: bool = False


class TtyGauge(Protocol):
    """How long the host's tty layer is holding bytes back (``TtyProbe``)."""

    def held_s(self, window_s: float) -> float:
        """The longest a byte was held among those in flight during the last
        ``window_s`` (one still in flight: until now); 0 without evidence."""
        ...


class LinkSession(Protocol):
    """What a device's link does for its ``LinkEngine`` (the engine calls these)."""

    async def run_session(self, channel: ByteChannel) -> None:
        """Probe the devices, then serve jobs and poll until the channel fails."""

    def link_down(self) -> None:
        """Mark every axis offline (called after a session ended)."""

    def wire_limit_hz(self) -> float:
        """Telemetry samples/s per axis the wire allows for the current poll set."""

    def achieved_rate_hz(self) -> float:
        """Telemetry samples/s per axis achieved recently."""


class HasEngine(Protocol):
    """A device link that has a ``LinkEngine``."""

    @property
    def engine(self) -> LinkEngine: ...


class FromEngine(Generic[T]):
    """A read-only member of a device link that is the member of the same name of its
    ``engine``, read each time (``engine_face``)."""

    def __init__(self, name: str, read: Callable[[LinkEngine], T]) -> None:
        self._name = name
        self._read = read

    def __set_name__(self, owner: type, name: str) -> None:
        if name != self._name:
            raise TypeError(f"{owner.__name__}.{name} would read the engine's {self._name}")

    @overload
    def __get__(self, link: None, owner: type) -> FromEngine[T]: ...

    @overload
    def __get__(self, link: HasEngine, owner: type | None = None) -> T: ...

    def __get__(self, link: HasEngine | None, owner: type | None = None) -> T | FromEngine[T]:
        if link is None:
            return self
        return self._read(link.engine)


def engine_face() -> tuple[
    FromEngine[str],
    FromEngine[str],
    FromEngine[int],
    FromEngine[LinkState],
    FromEngine[int],
    FromEngine[dict[str, int]],
    FromEngine[float | None],
    FromEngine[Callable[[], float]],
    FromEngine[Callable[[], Coroutine[Any, Any, None]]],
]:
    """The members of ``link.base.Link`` (and ``HasCounters``, ``HasWireBusy``,
    ``WireStats``) that a serial link takes from its engine, in this order:
    ``id, path, baud, state, errors, counters, wire_busy, now, run = engine_face()`` in
    the link's class body (``HasEngine``). The device link writes only what differs
    (``device``, ``axes``, its rates); no forwarding property per member, no base class.
    A name out of order fails when the class is defined."""
    return (
        FromEngine("id", lambda engine: engine.id),
        FromEngine("path", lambda engine: engine.path),
        FromEngine("baud", lambda engine: engine.baud),
        FromEngine("state", lambda engine: engine.state),
        FromEngine("errors", lambda engine: engine.errors),
        FromEngine("counters", lambda engine: engine.counters),
        FromEngine("wire_busy", lambda engine: engine.wire_busy),
        FromEngine("now", lambda engine: engine.now),
        FromEngine("run", lambda engine: engine.run),
    )


class LinkEngine:
    """The owner task, job queues, reconnects and status of one link; see the module
    docstring. Its device's link owns it and is its ``LinkSession``; only the owner
    task (inside ``run_session``) calls the members that touch the line."""

    def __init__(
        self,
        link_id: str,
        path: str,
        baud: int,
        connector: Connector,
        sink: DriverSink,
        session: LinkSession,
        *,
        clock: Callable[[], float] = time.monotonic,
        reconnect_max_s: float = 5.0,
        tty_gauge: TtyGauge | None = None,
    ) -> None:
        self._link_id = link_id
        self._path = path
        self._baud = baud
        self.connector = connector
        self.sink = sink
        self._session = session
        self.clock = clock
        self._reconnect_max_s = reconnect_max_s
        self._channel: ByteChannel | None = None
        self._state: LinkState = "connecting"
        self._message = ""
        self._errors = 0
        self._urgent: deque[Job] = deque()
        self._normal: deque[Job] = deque()
        self._wakeup = asyncio.Event()
        # A session reached ``connected`` since start (the device's link sets it):
        # a later outage shows ``disconnected``, not ``error``.
        self.connected_once = False
        self._counters: dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        # (when an exchange ended, the wire time it took), the last RATE_WINDOW_S of
        # them, and when the current session's channel opened (see ``wire_busy``).
        self._wire_log: deque[tuple[float, float]] = deque()
        self._opened_at: float | None = None
        # The silence rule: when the device last answered, and the requests since.
        self._last_answer_t: float | None = None
        self._unanswered = 0
        # The first timeout a host stall excused since the device last answered.
        self._stall_excused_since: float | None = None
        # The host tty layer's gauge: the one given, else a canary run by ``run``.
        self._tty_gauge: TtyGauge | None = tty_gauge
        self._own_probe = tty_gauge is None

    # --- Link protocol ----------------------------------------------------------------

    @property
    def id(self) -> str:
        return self._link_id

    @property
    def path(self) -> str:
        return self._path

    @property
    def baud(self) -> int:
        return self._baud

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def message(self) -> str:
        """What the state says (the port, the error)."""
        return self._message

    @property
    def channel(self) -> ByteChannel | None:
        """The open channel while a session runs, else None."""
        return self._channel

    def now(self) -> float:
        """The link's clock (the times of its samples and latches)."""
        return self.clock()

    @property
    def errors(self) -> int:
        """Wire errors since start: timeouts, bad echoes or checksums, stray bytes."""
        return self._errors

    @property
    def counters(self) -> dict[str, int]:
        """Retried, resynchronised and dropped things since start (see COUNTER_NAMES)."""
        return dict(self._counters)

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to counter ``name`` (``n`` 0 declares it)."""
        self._counters[name] = self._counters.get(name, 0) + n

    def add_error(self) -> None:
        """One more wire error (see ``errors``)."""
        self._errors += 1

    def wire_used(self, busy_s: float) -> None:
        """An exchange just ended that kept the line busy for ``busy_s`` (its characters
        at 10 bit times each, both directions as the device's protocol serialises them)."""
        now = self.clock()
        log = self._wire_log
        log.append((now, busy_s))
        while log and now - log[0][0] > RATE_WINDOW_S:
            log.popleft()

    @property
    def wire_busy(self) -> float | None:
        """The share (0..1) of the last ``RATE_WINDOW_S`` the line was busy with this
        link's exchanges, or ``None`` while no channel is open.

        Counted from the characters of each exchange that ended in the window (one that
        began before the window counts whole, hence the cap at 1), over the window or
        the time since the channel opened if that is shorter. A link that loses no
        time between exchanges approaches 1 whatever it carries; the sample rate over
        ``wire_limit_hz`` cannot, while commands share the wire with the polls.
        """
        if self._channel is None or self._opened_at is None:
            return None
        now = self.clock()
        span_s = min(RATE_WINDOW_S, now - self._opened_at)
        if span_s <= 0:
            return None
        busy_s = sum(b for t, b in self._wire_log if now - t <= RATE_WINDOW_S)
        return min(1.0, busy_s / span_s)

    async def run(self) -> None:
        """Connect, run sessions and reconnect with backoff until cancelled.

        Never returns and never raises but ``CancelledError``: a session that fails
        for any reason is reported and started again (see the module docstring).
        """
        ticker = asyncio.create_task(self._status_ticker(), name=f"status of link {self.id}")
        probe = TtyProbe() if self._own_probe else None
        if probe is not None and probe.start():
            self._tty_gauge = probe
        try:
            await self._supervise()
        finally:
            ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ticker
            if probe is not None:
                if self._tty_gauge is probe:
                    self._tty_gauge = None
                await probe.close()

    async def _status_ticker(self) -> None:
        while True:
            await asyncio.sleep(STATUS_PERIOD_S)
            self._check_silent()
            self._publish_status()

    # --- the silence rule (module docstring) -------------------------------------------

    def device_answered(self) -> None:
        """The device answered: host stalls may excuse timeouts again."""
        self._stall_excused_since = None

    def answered(self) -> None:
        """The device answered a request validly."""
        self._last_answer_t = self.clock()
        self._unanswered = 0
        self.device_answered()

    def unanswered_request(self, waited_s: float | None = None) -> None:
        """A request got no answer at all within its timeout (``waited_s``: that
        timeout; a host that stalled longer than that does not count it, see
        ``host_stalled``)."""
        if waited_s is not None and self.host_stalled(waited_s):
            return
        self._unanswered += 1
        self._check_silent()

    def host_stalled(self, waited_s: float) -> bool:
        """A read that timed out since the last check (``take_timeout_late_s``) was
        noticed more than ``waited_s`` (the time a request listens) after its deadline,
        or the host's tty layer held a byte for longer than that during the last
        ``waited_s`` (``TtyGauge``): the host itself was away for longer than it
        listened, so the silence is no evidence against the device - its answer may
        be held up in the host's tty layer, starved along with the host (measured:
        docs/simulator.md, "Under load"). Counted (``host_stalls``) and logged, never
        an alarm: a line that is really down shows at its next timeouts noticed on
        time (the server's own stalls are shown by the hub's status watch), and on a
        host that stalls all the time once ``HOST_STALL_EXCUSE_S`` (on the tty layer's
        evidence ``TTY_STALL_EXCUSE_S``) have passed since the first excused timeout
        without an answer (``device_answered`` ends the run)."""
        channel = self._channel
        late_s = 0.0 if channel is None else channel.take_timeout_late_s()
        gauge = self._tty_gauge
        held_s = 0.0 if gauge is None else gauge.held_s(waited_s)
        if late_s <= waited_s and held_s <= waited_s:
            return False
        bound_s = TTY_STALL_EXCUSE_S if held_s > waited_s else HOST_STALL_EXCUSE_S
        now = self.clock()
        if self._stall_excused_since is None:
            self._stall_excused_since = now
        elif now - self._stall_excused_since >= bound_s:
            return False
        self.count("host_stalls")
        logger.info(
            "link %s: a timeout noticed %.0f ms late, the host's tty layer holding bytes "
            "for %.0f ms (the host stalled): not counted against the device",
            self.id,
            1000 * late_s,
            1000 * held_s,
        )
        return True

    @property
    def host_stall_count(self) -> int:
        """Timeouts excused by ``host_stalled`` so far (a device's own rules compare it
        before and after a poll cycle: one excused timeout excuses the cycle)."""
        return self._counters.get("host_stalls", 0)

    def _check_silent(self) -> None:
        if self._channel is None or self._state not in ("connected", "error"):
            return
        since = self._last_answer_t if self._last_answer_t is not None else self._opened_at
        if since is None or self._unanswered < SILENT_REQUESTS:
            return
        silent_s = self.clock() - since
        if silent_s < SILENT_S:
            return
        message = (
            f"{_SILENT_PREFIX} {silent_s:.0f} s ({self._unanswered} requests in a row "
            "unanswered): is it powered, is the cable in?"
        )
        if self._state == "connected":
            self.sink.on_event("error", None, f"{self.id}: {message}")
            self.set_state("error", message)
        elif self._message.startswith(_SILENT_PREFIX):
            self.set_state("error", message)  # the same error, its time brought up

    async def _supervise(self) -> None:
        backoff_s = 0.25
        while True:
            try:
                channel = await self.connector.open()
            except LinkClosedError as exc:
                self.set_state("disconnected" if self.connected_once else "error", str(exc))
                self._fail_jobs(LinkDownError(f"link {self.id} is down"))
                await asyncio.sleep(backoff_s)
                backoff_s = min(backoff_s * 2, self._reconnect_max_s)
                continue
            self._opened_at = opened_at = self.clock()
            self._channel = channel
            self._wire_log.clear()
            self._last_answer_t, self._unanswered = None, 0
            try:
                await self._session.run_session(channel)
            except LinkClosedError as exc:
                self.sink.on_event("error", None, f"{self.id}: link lost: {exc}")
                self.set_state("reconnecting", f"link lost: {exc}")
            except Exception as exc:
                # Supervision: whatever escaped the session (a bug, a reply nobody
                # foresaw) must neither kill the link nor leave it shown as connected.
                logger.exception("link %s: session ended by an internal error", self.id)
                self.count("restarts")
                message = f"internal error: {type(exc).__name__}: {exc}; reconnecting"
                self.sink.on_event("error", None, f"{self.id}: {message}")
                self.set_state("error", message)
            finally:
                self._channel = None
                self._fail_jobs(LinkDownError(f"link {self.id} is down"))
                self._session.link_down()
                with contextlib.suppress(Exception):
                    await channel.close()
            # A port that opens and fails at once (an adapter that enumerates, then
            # errors) must not make this loop spin: back off unless the session ran.
            if self.clock() - opened_at < 5.0:
                await asyncio.sleep(backoff_s)
                backoff_s = min(backoff_s * 2, self._reconnect_max_s)
            else:
                backoff_s = 0.25

    # --- jobs -------------------------------------------------------------------------

    async def submit(
        self,
        run: Callable[[], Awaitable[T]],
        *,
        urgent: bool = False,
        axis: int | None = None,
        motion: bool = False,
        stop: bool = False,
    ) -> T:
        """Run ``run`` on the owner task with exclusive use of the line.

        ``motion`` marks a job that may move ``axis`` (a command, a raw console
        line). A ``stop`` job (always urgent) first fails every queued motion job of
        its axis (``axis=None``: of every axis) with "not sent": a move queued a
        moment before the user pressed STOP must never run after it.
        """
        if self._channel is None or self._state not in ("connected", "error"):
            raise LinkDownError(f"link {self.id} is {self._state}: nothing was sent")
        if stop:
            urgent = True
            self._cancel_motion(axis)
        future: asyncio.Future[object] = asyncio.get_running_loop().create_future()
        job = Job(run, future, axis, motion)
        (self._urgent if urgent else self._normal).append(job)
        self._wakeup.set()
        result = await future
        return result  # type: ignore[return-value]

    async def let_stops_pass(self) -> None:
        """Run the urgent jobs (STOPs) waiting now, inside a long job that has no motion
        of its own (a write or read of several parameters), between two of its
        exchanges: a STOP then waits for one exchange, not for the whole job. The job
        goes on afterwards (its exchanges select their module again as needed)."""
        while self._urgent:
            await self.run_job(self._urgent.popleft())

    @property
    def urgent_pending(self) -> bool:
        """A stop is waiting: a poll sequence should give the line up now."""
        return bool(self._urgent)

    @property
    def jobs_pending(self) -> bool:
        return bool(self._urgent or self._normal)

    def take_job(self) -> Job | None:
        """The next job: an urgent one (a stop) first, else a user job, else None."""
        if self._urgent:
            return self._urgent.popleft()
        if self._normal:
            return self._normal.popleft()
        return None

    def _cancel_motion(self, axis: int | None) -> None:
        kept: deque[Job] = deque()
        for job in self._normal:
            if job.motion and (axis is None or job.axis == axis):
                if not job.future.done():
                    job.future.set_exception(
                        DeviceRefusedError("not sent: STOP was pressed before it went out")
                    )
            else:
                kept.append(job)
        self._normal = kept

    def _fail_jobs(self, error: Exception) -> None:
        for queue in (self._urgent, self._normal):
            while queue:
                job = queue.popleft()
                if not job.future.done():
                    job.future.set_exception(error)

    async def run_job(self, job: Job) -> None:
        """Run ``job`` and deliver its result or error to its submitter."""
        if job.future.done():  # the caller gave up (cancelled)
            return
        try:
            result = await job.run()
        except LinkClosedError:
            job.future.set_exception(LinkDownError(f"link {self.id} was lost"))
            raise
        except Exception as exc:  # delivered to the caller, who reports it
            if not job.future.done():
                job.future.set_exception(exc)
        else:
            if not job.future.done():
                job.future.set_result(result)

    async def wait_job_or(self, timeout_s: float) -> None:
        """Sleep until a job is submitted or ``timeout_s`` passed."""
        self._wakeup.clear()
        if self.jobs_pending:
            return
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                await self._wakeup.wait()

    def wake(self) -> None:
        """Wake a session waiting in ``wait_job_or`` (something it polls changed)."""
        self._wakeup.set()

    def require_channel(self) -> ByteChannel:
        """The open channel; ``LinkClosedError`` when none is."""
        if self._channel is None:
            raise LinkClosedError(f"link {self.id} is not open")
        return self._channel

    # --- status -----------------------------------------------------------------------

    def set_state(self, state: LinkState, message: str) -> None:
        """Show the link ``state`` with ``message``; published when either changed."""
        changed = state != self._state or message != self._message
        self._state, self._message = state, message
        if changed:
            self._publish_status()

    def _publish_status(self) -> None:
        if self._channel is None and self._state == "connected":
            # Never shown connected without an open channel (the session has ended).
            self._state = "reconnecting"
        self.sink.on_link_status(
            self.id,
            self._state,
            self._message,
            self._session.achieved_rate_hz(),
            self._session.wire_limit_hz(),
            self._errors,
        )
