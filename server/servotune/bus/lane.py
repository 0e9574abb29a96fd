"""The hub's safety lane: keep-alives, STOPs, the rigs' presence and clock probes on a
NATS connection and an event loop of their own, in a thread of their own.

Why a thread: the hub's event loop also takes in every rig's telemetry, fans it out
to the browsers and serves the api; a rig that floods telemetry (or a busy moment of
the hub) delayed the keep-alives past a rig's dead-man lease and stopped a move the
hub had started, and delayed presence until rigs were shown offline (keep-alive gaps
longer than a 350 ms lease under another rig's 5,000 samples/s). NATS has no
priorities and one connection is one FIFO: the lane's connection carries nothing but
this traffic, and its loop runs nothing but it, so a backlog elsewhere in the hub
cannot hold it back (the interpreter lock is handed over every few milliseconds).

The keep-alives say "this hub can act": they go out only while the hub's own loop
turns (``main_turned``, at least every ``MAIN_STALL_MAX_S``). A hub whose loop hangs
stops them, and the rigs' dead-man stops what it set in motion (an independent sender
would keep that motion alive with nobody able to stop it from the hub). A round that
goes out late is logged with how much of the delay the lane's thread spent waiting for
a CPU, and how long the hub's main thread did (Linux ``schedstat``): the lane needs
the interpreter lock, which the main thread holds while it runs Python, so a main
thread the kernel preempted holding it holds the lane back too (on an overloaded
machine: not something the hub did).

What the lane decides, per rig (``RigLiveness``): present or not (its presence,
dated with the rig's clock as estimated from round trips, ``bus.clock``; a presence
older than ``offline_after_s`` when it arrives is old news, not a sign of life), the
rig's clock (a ``cmd.clock`` probe when a new run of the rig agent is heard, then every
``CLOCK_PROBE_PERIOD_S``) and the hub session the rig knows it by. The hub's loop
reads those (``RemoteLink``); every compound read or write holds the liveness' lock.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import os
import secrets
import threading
import time
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.errors import Error as NatsError

from servotune.bus import subjects
from servotune.bus.clock import RigClock
from servotune.bus.connection import BusSettings, connect_bus, role_settings
from servotune.bus.messages import KeepAlive
from servotune.bus.tasks import BackgroundTasks

logger = logging.getLogger(__name__)

T = TypeVar("T")


def cpu_wait_s(thread: int | None = None) -> float | None:
    """How long a thread of this process (this one by default) has waited for a CPU
    while runnable, in all (Linux ``schedstat``: time on CPU, time waiting on a run
    queue, slices); None where the kernel does not say."""
    path = (
        "/proc/thread-self/schedstat" if thread is None else f"/proc/self/task/{thread}/schedstat"
    )
    try:
        with open(path) as stat:
            return int(stat.read().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return None


# The hub's loop must have turned this recently for the keep-alives to go out.
MAIN_STALL_MAX_S = 1.0
# The lane's loop notes the time this often (``heard_until``).
LANE_TICK_S = 0.02
# How often a present rig's clock is probed again (each probe narrows the estimate and
# follows the clocks' drift), and how long a probe may take. While the estimate is
# wider than CLOCK_WIDE_S (only slow round trips so far: a loaded machine) it is
# probed every CLOCK_PROBE_SOON_S.
CLOCK_PROBE_PERIOD_S = 5.0
CLOCK_WIDE_S = 0.05
CLOCK_PROBE_SOON_S = 0.5
CLOCK_PROBE_TIMEOUT_S = 1.0


# The lane's thread asks the kernel for this much more of the CPU than the hub's other
# threads get (a negative nice value, Linux: per thread). Needs CAP_SYS_NICE (root, or
# granted by the service manager); without it the lane runs at the hub's priority.
LANE_NICE = -10


def _raise_priority() -> None:
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), LANE_NICE)
    except (OSError, AttributeError) as exc:
        logger.info("bus: the safety lane runs at the hub's own priority (%s)", exc)
    else:
        logger.info("bus: the safety lane's thread runs at nice %d", LANE_NICE)


class RigLiveness:
    """One rig as the lane hears it. Written by the lane's thread, read by the hub's
    loop; ``clock`` is the hub's monotonic clock (injected in tests)."""

    def __init__(
        self, rig: str, offline_after_s: float, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.rig = rig
        self.offline_after_s = offline_after_s
        self._clock = clock
        self._lock = threading.Lock()
        # The rig agent's run whose clock ``rig_clock`` estimates (None: none yet).
        self.instance: str | None = None
        self.rig_clock = RigClock()
        # Hub clock of the latest moment the rig is known to have been alive.
        self.seen_at = 0.0
        self.online = False
        # Hub clock when the hub last showed the rig offline: proof of life from
        # before that does not bring it back (None: shown present since).
        self.offline_at: float | None = None
        # Bumped whenever the rig turns present: the hub asks it for a fresh snapshot.
        self.returns = 0
        # Listed by the hub (it sends this rig keep-alives).
        self.listed = False
        # The hub session this rig knows (renewed when the rig's dead-man ended it).
        self.session = secrets.token_hex(16)
        self.last_probe = -math.inf
        self.probing = False
        # Counters (tests, benchmarks, the link's status).
        self.presences = 0
        self.stale_presences = 0
        self.probes = 0

    # --- read by the hub's loop ----------------------------------------------------

    def present(self, now: float | None = None) -> bool:
        now = self._clock() if now is None else now
        with self._lock:
            return self.online and now - self.seen_at <= self.offline_after_s

    def clock_bounds(self, now: float | None = None) -> tuple[float, float] | None:
        """The offset ``rig clock - hub clock`` as ``(low, high)``, None if unknown."""
        now = self._clock() if now is None else now
        with self._lock:
            if not self.rig_clock.known:
                return None
            return self.rig_clock.bounds(now)

    def shown_offline(self, now: float | None = None) -> None:
        with self._lock:
            self.offline_at = self._clock() if now is None else now

    def renew_session(self, ended: str) -> str:
        """The rig ended session ``ended``: a new one (once, whoever asks first)."""
        with self._lock:
            if self.session == ended:
                self.session = secrets.token_hex(16)
            return self.session

    # --- written by the lane --------------------------------------------------------

    def on_presence(self, rig_now: float | None, instance: str | None, now: float) -> bool:
        """A presence; True if the rig's clock must be probed before it can count."""
        with self._lock:
            self.presences += 1
            if rig_now is None or instance is None:
                return False  # cannot be dated: not counted (a rig of an older version)
            if instance != self.instance or not self.rig_clock.known:
                return True
            # Sent when the estimate says (the middle of its interval, off by at most
            # half its width: milliseconds once a quick round trip came back; probes
            # follow each other quickly while it is wide, ``_probes``).
            sent = min(now, self.rig_clock.to_hub(rig_now, now))
            if now - sent > self.offline_after_s:
                self.stale_presences += 1
                return False
            self._seen(sent, now)
            return now - self.last_probe > CLOCK_PROBE_PERIOD_S

    def on_gone(self, instance: str | None) -> None:
        """The rig left cleanly: offline now (a leftover of an earlier run does not count)."""
        with self._lock:
            if instance is None or instance == self.instance:
                self.online = False

    def on_probe(self, sent: float, rig_now: float, instance: str, received: float) -> None:
        """A clock probe came back: the clock, and proof the rig was alive after ``sent``."""
        with self._lock:
            if instance != self.instance:
                self.instance = instance
                self.rig_clock.reset()
            if not self.rig_clock.add(sent, rig_now, received):
                logger.warning("rig %s: its clock moved; estimated again", self.rig)
            self.probes += 1
            self._seen(sent, received)

    def _seen(self, at: float, now: float) -> None:
        if at <= self.seen_at:
            return
        if self.offline_at is not None and at <= self.offline_at:
            return  # from before the rig was shown offline: old news
        was = self.online and now - self.seen_at <= self.offline_after_s
        self.seen_at = at
        self.online = True
        if now - at <= self.offline_after_s:
            self.offline_at = None
            if not was:
                self.returns += 1


class SafetyLane:
    """The lane's thread, loop and connection (the hub's ``stop`` NATS user)."""

    def __init__(
        self,
        settings: BusSettings,
        hub_name: str,
        on_unknown: Callable[[str], None],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._settings = settings
        self._hub_name = hub_name
        self._on_unknown = on_unknown
        self._clock = clock
        self._rigs: dict[str, RigLiveness] = {}
        self._rigs_lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._main_loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._nc: Client | None = None
        self._done: asyncio.Event | None = None
        self._tasks = BackgroundTasks(logger)
        # Keep-alive rounds: the longest gap between two, and the longest part of a gap
        # not spent waiting for a CPU (what the hub itself could have caused).
        self.keepalive_max_gap_s = 0.0
        self.keepalive_max_cpu_wait_s = 0.0
        self.keepalive_max_unexplained_s = 0.0
        self.keepalive_rounds = 0
        self.keepalives_withheld = 0
        # The hub's loop's last turn (hub clock; ``main_turned``).
        self._main_turn = clock()
        # The lane's own loop's last turn (hub clock): what it has heard is current up
        # to about then (``heard_until``).
        self.turned_at = clock()
        self._main_thread: int | None = None
        self._logged_at = -math.inf

    # --- lifespan (called from the hub's loop) ------------------------------------------

    async def start(self) -> None:
        """Start the thread and connect; raises what connecting raised."""
        self._main_loop = asyncio.get_running_loop()
        self._main_thread = threading.get_native_id()
        ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._thread = threading.Thread(
            target=self._run, args=(ready,), name="bus safety lane", daemon=True
        )
        self._thread.start()
        await asyncio.wrap_future(ready)

    async def stop(self) -> None:
        loop, done = self._loop, self._done
        if loop is not None and done is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(done.set)
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 10)
            self._thread = None

    def heard_until(self, at: float) -> bool:
        """Has the lane's loop run for two ticks after ``at`` (hub clock), so
        that whatever a rig sent before then has been read? A silence is judged only
        then: a hub whose own threads were held up (an overloaded machine) must not show
        a rig offline whose presences it has not read yet. A lane that stopped turning
        (5 s) is not waited for."""
        turned = self.turned_at
        return turned >= at + 2 * LANE_TICK_S or self._clock() - turned > 5.0

    def main_turned(self) -> None:
        """The hub's loop is turning (called from it every ``keepalive_period_s``)."""
        self._main_turn = self._clock()

    def liveness(self, rig: str) -> RigLiveness:
        with self._rigs_lock:
            known = self._rigs.get(rig)
            if known is None:
                known = RigLiveness(rig, self._settings.offline_after_s, self._clock)
                self._rigs[rig] = known
            return known

    def list_rig(self, rig: str) -> RigLiveness:
        """The hub lists ``rig``: keep-alives go to it from now on."""
        live = self.liveness(rig)
        live.listed = True
        return live

    async def request(self, subject: str, data: bytes, timeout_s: float) -> Msg:
        """A request on the lane's connection (a STOP), from the hub's loop."""
        return await self._call(self._request(subject, data, timeout_s))

    async def _call(self, job: Coroutine[Any, Any, T]) -> T:
        loop = self._loop
        if loop is None or loop.is_closed():
            job.close()
            raise NatsError("the hub's safety lane is not running")
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(job, loop))

    # --- the thread -----------------------------------------------------------------------

    def _run(self, ready: concurrent.futures.Future[None]) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main(ready))
        finally:
            loop.close()

    async def _main(self, ready: concurrent.futures.Future[None]) -> None:
        self._done = asyncio.Event()
        _raise_priority()
        try:
            self._nc = await connect_bus(
                role_settings(self._settings, "stop"), name=f"hub-{self._hub_name}-stop"
            )
            # Every rig's presence (a leaf rig's too: nats-server 2.9.10 carries this
            # subscription across a leaf link, checked in tests/integration/bus/test_leaf.py).
            await self._nc.subscribe(subjects.PRESENCE_SUBJECTS, cb=self._on_presence)
            await self._nc.flush()
        except BaseException as exc:
            ready.set_exception(exc)
            if self._nc is not None:
                with contextlib.suppress(NatsError, TimeoutError, OSError):
                    await self._nc.close()
            return
        ready.set_result(None)
        self._tasks.spawn(self._keepalives(), "bus lane: keep-alives")
        self._tasks.spawn(self._ticks(), "bus lane: ticks")
        self._tasks.spawn(self._probes(), "bus lane: clock probes")
        await self._done.wait()
        await self._tasks.cancel_all()
        logger.info("bus: %s", self.summary())
        with contextlib.suppress(NatsError, TimeoutError, OSError):
            await self._nc.close()

    async def _request(self, subject: str, data: bytes, timeout_s: float) -> Msg:
        assert self._nc is not None
        return await self._nc.request(subject, data, timeout=timeout_s)

    async def _keepalives(self) -> None:
        """Every ``keepalive_period_s``, to every listed rig, present or not (the rig's
        dead-man decides on what arrives, not on what the hub believes of the rig),
        while the hub's loop turns."""
        assert self._nc is not None
        period = self._settings.keepalive_period_s
        last, waited = self._clock(), self._cpu_waits()
        while True:
            now = self._clock()
            stalled_s = now - self._main_turn
            with self._rigs_lock:
                rigs = [live for live in self._rigs.values() if live.listed]
            if stalled_s > MAIN_STALL_MAX_S:
                self.keepalives_withheld += 1
                self._log_late(
                    f"the hub's loop has not turned for {stalled_s:.1f} s: keep-alives withheld "
                    "(the rigs' dead-man stops what this hub set in motion)"
                )
                rigs = []
            for live in rigs:
                body = KeepAlive(session=live.session, hub=self._hub_name)
                with contextlib.suppress(NatsError):
                    await self._nc.publish(
                        subjects.rig_cmd(live.rig, "keepalive"), body.model_dump_json().encode()
                    )
            waited_now = self._cpu_waits()
            cpu_s = waited_now - waited
            if self.keepalive_rounds:
                gap = now - last
                self.keepalive_max_gap_s = max(self.keepalive_max_gap_s, gap)
                self.keepalive_max_cpu_wait_s = max(self.keepalive_max_cpu_wait_s, cpu_s)
                unexplained = gap - cpu_s
                self.keepalive_max_unexplained_s = max(
                    self.keepalive_max_unexplained_s, unexplained
                )
                if gap > 3 * period:
                    self._log_late(
                        f"keep-alives went out {1000 * gap:.0f} ms apart (every "
                        f"{1000 * period:.0f} ms wanted); this thread and the hub's main "
                        f"thread waited {1000 * cpu_s:.0f} ms of it for a CPU"
                    )
            self.keepalive_rounds += 1
            last, waited = now, waited_now
            await asyncio.sleep(period)

    async def _ticks(self) -> None:
        """``turned_at``, every ``LANE_TICK_S``: the lane's loop keeps time."""
        while True:
            self.turned_at = self._clock()
            await asyncio.sleep(LANE_TICK_S)

    def _cpu_waits(self) -> float:
        """This thread's and the hub's main thread's waits for a CPU, in all."""
        own = cpu_wait_s() or 0.0
        main = cpu_wait_s(self._main_thread) if self._main_thread is not None else None
        return own + (main or 0.0)

    def _log_late(self, text: str) -> None:
        if self._clock() - self._logged_at >= 10.0:
            self._logged_at = self._clock()
            logger.warning("bus: %s", text)

    def summary(self) -> str:
        return (
            f"keep-alive rounds {self.keepalive_rounds}: longest gap "
            f"{1000 * self.keepalive_max_gap_s:.0f} ms, longest wait for a CPU "
            f"{1000 * self.keepalive_max_cpu_wait_s:.0f} ms (the lane's and the main "
            "thread's), longest gap not spent waiting for a CPU "
            f"{1000 * self.keepalive_max_unexplained_s:.0f} ms; "
            f"withheld {self.keepalives_withheld} (the hub's loop stalled)"
        )

    async def _on_presence(self, msg: Msg) -> None:
        tokens = msg.subject.split(".")
        if len(tokens) != 4 or not subjects.check_token_ok(tokens[2]):
            return
        rig = tokens[2]
        headers = msg.headers or {}
        instance = headers.get(subjects.RIG_ID_HEADER)
        rig_now: float | None = None
        with contextlib.suppress(TypeError, ValueError):
            rig_now = float(headers.get(subjects.RIG_NOW_HEADER, ""))
        with self._rigs_lock:
            known = rig in self._rigs
        live = self.liveness(rig)
        if headers.get(subjects.GONE_HEADER):
            live.on_gone(instance)
            return
        if not known or not live.listed:
            assert self._main_loop is not None
            with contextlib.suppress(RuntimeError):  # the hub's loop is closing
                self._main_loop.call_soon_threadsafe(self._on_unknown, rig)
        if live.on_presence(rig_now, instance, self._clock()):
            self._probe_soon(live)

    async def _probes(self) -> None:
        """Present rigs' clocks, every ``CLOCK_PROBE_PERIOD_S``."""
        while True:
            await asyncio.sleep(0.5)
            now = self._clock()
            with self._rigs_lock:
                rigs = list(self._rigs.values())
            for live in rigs:
                if not live.present(now):
                    continue
                bounds = live.clock_bounds(now)
                wide = bounds is None or bounds[1] - bounds[0] > CLOCK_WIDE_S
                period = CLOCK_PROBE_SOON_S if wide else CLOCK_PROBE_PERIOD_S
                if now - live.last_probe > period:
                    self._probe_soon(live)

    def _probe_soon(self, live: RigLiveness) -> None:
        if live.probing:
            return
        live.probing = True
        self._tasks.spawn(self._probe(live), f"bus lane: clock of {live.rig}")

    async def _probe(self, live: RigLiveness) -> None:
        assert self._nc is not None
        try:
            sent = self._clock()
            live.last_probe = sent
            try:
                msg = await self._nc.request(
                    subjects.rig_cmd(live.rig, subjects.CLOCK), b"", timeout=CLOCK_PROBE_TIMEOUT_S
                )
            except (NatsError, TimeoutError) as exc:
                logger.debug("rig %s: clock probe failed (%s)", live.rig, exc)
                return
            received = self._clock()
            headers = msg.headers or {}
            instance = headers.get(subjects.RIG_ID_HEADER)
            try:
                rig_now = float(headers.get(subjects.RIG_NOW_HEADER, ""))
            except ValueError:
                rig_now = math.nan
            if instance is None or not math.isfinite(rig_now):
                logger.warning("rig %s: its clock answer is not understood", live.rig)
                return
            live.on_probe(sent, rig_now, instance, received)
        finally:
            live.probing = False
