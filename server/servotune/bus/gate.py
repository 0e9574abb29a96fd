"""The rigs' telemetry on its way into the hub: fair, bounded, newest first.

Every rig's telemetry batches wait here (the subscription callback only queues them)
until the hub's pump takes them, every ``PUMP_PERIOD_S``:

* per rig at most ``bytes_per_s`` (a token bucket holding ``BURST_S`` of it): when a
  rig sends more, its *oldest* batches are shed, never the newest, and never another
  rig's (a rig flooding its own subjects costs only itself);
* a batch that waited longer than ``max_wait_s`` is shed unread (it would not be
  shown live anyway, ``remote.LIVE_MAX_AGE_S``): a hub that cannot keep up sheds old
  telemetry instead of falling behind;
* the pump spends at most ``busy_fraction`` of each period on it, taking the rigs in
  turn, so the hub's loop keeps time for everything else (the api, the fan-out).

What was shed is counted per rig and handed back (``on_shed``) for the link's counters.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")

PUMP_PERIOD_S = 0.02
BURST_S = 0.5


@dataclass(slots=True)
class _Queue(Generic[T]):
    items: deque[tuple[float, int, T]] = field(default_factory=deque)
    queued_bytes: int = 0
    tokens: float = 0.0
    refilled_at: float = 0.0
    # The newest items within the budget, oldest first: what the pump delivers next.
    ready: deque[tuple[float, int, T]] = field(default_factory=deque)


class TelemetryGate(Generic[T]):
    def __init__(
        self,
        bytes_per_s: float,
        *,
        max_wait_s: float,
        busy_fraction: float = 0.5,
        on_shed: Callable[[T], None] = lambda _: None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.bytes_per_s = bytes_per_s
        self.max_wait_s = max_wait_s
        self.busy_fraction = busy_fraction
        self._on_shed = on_shed
        self._clock = clock
        self._queues: dict[str, _Queue[T]] = {}
        self._turn = 0
        self.shed: dict[str, int] = {}
        self.delivered: dict[str, int] = {}

    def offer(self, rig: str, item: T, size: int) -> None:
        """Queue one batch of ``rig`` (from the subscription callback: cheap)."""
        queue = self._queues.get(rig)
        if queue is None:
            queue = self._queues[rig] = _Queue()
            queue.tokens = self.bytes_per_s * BURST_S
            queue.refilled_at = self._clock()
        queue.items.append((self._clock(), size, item))
        queue.queued_bytes += size
        # A bound on memory: never more than a second of the rig's budget queued.
        while queue.queued_bytes > self.bytes_per_s and len(queue.items) > 1:
            _, shed_size, shed = queue.items.popleft()
            queue.queued_bytes -= shed_size
            self._shed(rig, shed)

    def _shed(self, rig: str, item: T) -> None:
        self.shed[rig] = self.shed.get(rig, 0) + 1
        self._on_shed(item)

    def _select(self, rig: str, queue: _Queue[T], now: float) -> None:
        """Move what ``rig`` may deliver into ``ready``: the newest within its tokens;
        older ones and those that waited too long are shed."""
        queue.tokens = min(
            self.bytes_per_s * BURST_S,
            queue.tokens + self.bytes_per_s * (now - queue.refilled_at),
        )
        queue.refilled_at = now
        while queue.ready and now - queue.ready[0][0] > self.max_wait_s:
            self._shed(rig, queue.ready.popleft()[2])
        if not queue.items:
            return
        queue.queued_bytes = 0
        kept: list[tuple[float, int, T]] = []
        while queue.items:
            arrived, size, item = queue.items.pop()  # newest first
            if now - arrived <= self.max_wait_s and size <= queue.tokens:
                queue.tokens -= size
                kept.append((arrived, size, item))
            else:
                self._shed(rig, item)
                # Everything older goes too: the newest are kept, never a hole.
                while queue.items:
                    self._shed(rig, queue.items.pop()[2])
        queue.ready.extend(reversed(kept))

    def take(self, deliver: Callable[[str, T], None]) -> None:
        """One turn of the pump: select every rig's batches, then deliver them, the
        rigs in turn, until ``busy_fraction`` of a period is spent (the rest waits for
        the next turn, or is shed once it has waited ``max_wait_s``)."""
        now = self._clock()
        for rig, queue in self._queues.items():
            self._select(rig, queue, now)
        rigs = [rig for rig, queue in self._queues.items() if queue.ready]
        if not rigs:
            return
        self._turn = (self._turn + 1) % len(rigs)
        order = rigs[self._turn :] + rigs[: self._turn]
        until = now + self.busy_fraction * PUMP_PERIOD_S
        while order:
            for rig in list(order):
                queue = self._queues[rig]
                if not queue.ready:
                    order.remove(rig)
                    continue
                _, _, item = queue.ready.popleft()
                deliver(rig, item)
                self.delivered[rig] = self.delivered.get(rig, 0) + 1
            if self._clock() >= until:
                return
