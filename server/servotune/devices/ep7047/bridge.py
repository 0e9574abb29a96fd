"""The event-loop side of the EP7047-1032 cycle: the link's status, the sample batches
and the results of requests, posted from the cycle thread to the event loop.

``EventLoopBridge`` implements ``devices.ep7047.cycle.CycleReports``: the cycle thread calls
its ``post_*``/``resolve``/``reject`` methods, and each becomes one callback on the
loop (``loop.call_soon_threadsafe``), in the order the thread made them. Samples go in
batches (``SAMPLE_BATCH_S``); anything else first flushes the batch so far. Within a
cycle (``begin_cycle``..``end_cycle``) results wait for that cycle's sample.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import Any, Final

from servotune.devices.ep7047.requests import CycleCounters, _Request, _settle
from servotune.link.base import DriverSink, Sample
from servotune.link.engine import recent_rate_hz
from servotune.schema import AxisHealth, EventLevel, LinkState

SAMPLE_BATCH_S: Final = 0.02
"""Samples of the cycle thread go to the event loop in batches, one
``call_soon_threadsafe`` each ``SAMPLE_BATCH_S`` (10 samples at the 2 ms default
cycle) instead of one per cycle: every wake-up of the loop costs a self-pipe write,
an epoll round and a callback (docs/ep7047-driver.md, "CPU": the per-sample wake-ups
were the largest single cost of the demo server). 20 ms stays below
the hub's telemetry batch (``hub.state.BATCH_PERIOD_S``, 1/30 s), so every telemetry
message still carries new samples of this axis and the plots see no added delay
worth the name; every sample is still delivered, in order, with its own time.
Anything else the thread posts (a result, a state change, an event) first flushes
the batch, so a caller that gets its answer has the sample showing the drive's
reaction already delivered."""
SAMPLE_BATCH_MAX: Final = 32
"""A batch is flushed at this many samples even if its 20 ms are not up (1 ms cycle,
or a test clock that does not advance)."""


class EventLoopBridge:
    """The link's status and the posts from the cycle thread to the event loop.

    Loop side: ``attach`` (the running loop), ``state``/``message``/``set_state``,
    ``publish_status``, ``achieved_rate_hz``, ``fail``. Cycle-thread side: the
    ``CycleReports`` methods; before ``attach`` they are dropped (nobody listens).
    """

    def __init__(
        self,
        link_id: str,
        axis_id: str,
        sink: DriverSink,
        counters: CycleCounters,
        *,
        wire_limit_hz: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._link_id = link_id
        self._axis_id = axis_id
        self._sink = sink
        self._counters = counters
        self._wire_limit_hz = wire_limit_hz
        self._clock = clock
        self._state: LinkState = "connecting"
        self._message = ""
        self._sample_times: deque[float] = deque(maxlen=4096)
        self._loop: asyncio.AbstractEventLoop | None = None
        # cycle thread only: results held until the cycle's sample, samples not yet posted
        self._in_cycle = False
        self._outbox: list[tuple[_Request, Any, BaseException | None]] = []
        self._sample_batch: list[Sample] = []
        self._batch_due = 0.0

    # --- event loop side ----------------------------------------------------------------

    def attach(self, loop: asyncio.AbstractEventLoop) -> None:
        """Deliver the posts to ``loop`` from now on."""
        self._loop = loop

    @property
    def attached(self) -> bool:
        return self._loop is not None

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def message(self) -> str:
        return self._message

    def set_state(self, state: LinkState, message: str) -> None:
        """Set the link's state; publish the status when it changed."""
        changed = (state, message) != (self._state, self._message)
        self._state, self._message = state, message
        if changed:
            self.publish_status()

    def publish_status(self) -> None:
        self._sink.on_link_status(
            self._link_id,
            self._state,
            self._message,
            self.achieved_rate_hz(),
            self._wire_limit_hz,
            self._counters.errors,
        )

    def achieved_rate_hz(self) -> float:
        """Samples/s over the last 2 s, falling to 0 within 2 s when the cycles stop."""
        return recent_rate_hz(self._sample_times, self._clock())

    def fail(self, requests: Iterable[_Request], error: BaseException) -> None:
        """Fail ``requests`` with ``error`` (loop side: at once)."""
        for request in requests:
            _settle(request.future, None, error)

    def _deliver_samples(self, samples: list[Sample]) -> None:
        times = self._sample_times
        sink, axis_id = self._sink, self._axis_id
        for sample in samples:
            times.append(sample.t)
            sink.on_sample(axis_id, sample)

    # --- CycleReports (cycle thread side) -----------------------------------------------

    def begin_cycle(self) -> None:
        """Hold results until ``end_cycle`` (after the cycle's sample)."""
        self._in_cycle = True

    def end_cycle(self) -> None:
        """Post the results held since ``begin_cycle``."""
        self._in_cycle = False
        outbox, self._outbox = self._outbox, []
        for request, result, error in outbox:
            self._post(_settle, request.future, result, error)

    def post_sample(self, sample: Sample) -> None:
        """Queue ``sample`` for the loop; post the batch when it is due (SAMPLE_BATCH_S)."""
        batch = self._sample_batch
        batch.append(sample)
        now = time.monotonic()
        if len(batch) == 1:
            self._batch_due = now + SAMPLE_BATCH_S
        elif now >= self._batch_due or len(batch) >= SAMPLE_BATCH_MAX:
            self.flush_samples()

    def flush_samples(self) -> None:
        """Post the samples queued so far."""
        batch, self._sample_batch = self._sample_batch, []
        if batch:
            self._post_now(self._deliver_samples, batch)

    def resolve(self, request: _Request, result: object = None) -> None:
        self._settle_later(request, result, None)

    def reject(self, request: _Request, error: BaseException) -> None:
        self._settle_later(request, None, error)

    def post_state(self, state: LinkState, message: str) -> None:
        self._post(self.set_state, state, message)

    def post_event(self, level: EventLevel, message: str, *, axis: bool = True) -> None:
        self._post(self._sink.on_event, level, self._axis_id if axis else None, message)

    def post_health(self, health: AxisHealth, message: str) -> None:
        self._post(self._sink.on_axis_health, self._axis_id, health, message)

    def post_params(self, values: Mapping[str, int], source: str) -> None:
        self._post(self._sink.on_params, self._axis_id, dict(values), source)

    def _settle_later(self, request: _Request, result: Any, error: BaseException | None) -> None:
        # Within a cycle, results wait for that cycle's sample: a caller that gets its
        # answer has the sample showing the drive's reaction already delivered.
        if self._in_cycle:
            self._outbox.append((request, result, error))
        else:
            self._post(_settle, request.future, result, error)

    def _post(self, callback: Callable[..., object], *args: Any) -> None:
        """Run ``callback`` on the loop, after the samples so far."""
        if self._sample_batch:
            self.flush_samples()
        self._post_now(callback, *args)

    def _post_now(self, callback: Callable[..., object], *args: Any) -> None:
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop is closed: nobody listens
            loop.call_soon_threadsafe(callback, *args)
