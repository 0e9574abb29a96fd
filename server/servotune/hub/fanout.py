"""The fan-out of the hub's messages to its websocket clients.

Samples are batched per axis about 30 times a second and serialised once; every
websocket client has its own bounded queue. A slow client loses its oldest telemetry
batches (counted and reported to it), never status or events, and never slows the
serial side or the other clients.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from typing import Protocol

from pydantic import BaseModel

from servotune.schema import ClientStats

BATCH_PERIOD_S = 1 / 30
STATUS_PERIOD_S = 1.0
CLIENT_QUEUE_MESSAGES = 256


class ClientQueue:
    """Outgoing messages of one websocket client (JSON text), bounded.

    When full, the oldest *telemetry* message is dropped first; status, params and
    events are kept because a client must not miss a state change.
    """

    def __init__(self, max_messages: int = CLIENT_QUEUE_MESSAGES) -> None:
        self._items: deque[tuple[bool, str]] = deque()
        self._max = max_messages
        self._event = asyncio.Event()
        self.sent = 0
        self.dropped = 0

    def put(self, text: str, *, droppable: bool) -> None:
        self._items.append((droppable, text))
        while len(self._items) > self._max:
            for index, (is_droppable, _) in enumerate(self._items):
                if is_droppable:
                    del self._items[index]
                    self.dropped += 1
                    break
            else:
                # Only non-droppable messages: keep the newest ones.
                self._items.popleft()
                self.dropped += 1
        self._event.set()

    async def get(self) -> str:
        while not self._items:
            self._event.clear()
            await self._event.wait()
        self.sent += 1
        return self._items.popleft()[1]

    def __len__(self) -> int:
        return len(self._items)


class FanOutSource(Protocol):
    """What the fan-out's loop asks of the hub's state (``HubState``)."""

    def take_telemetry(self, build: bool) -> list[str]:
        """Take every axis' samples since the last call; the telemetry messages (JSON),
        one per axis that had samples, if ``build`` (else the samples are dropped)."""
        ...

    def status_tick(self, now: float) -> None:
        """Once every ``STATUS_PERIOD_S``: the hub's periodic judgements and repeats."""
        ...


class FanOut:
    """Every websocket client's queue, and the loop that sends the telemetry batches
    and, every ``STATUS_PERIOD_S``, each client its own counts (``ClientStats``)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._clients: set[ClientQueue] = set()

    def subscribe(self) -> ClientQueue:
        queue = ClientQueue()
        self._clients.add(queue)
        return queue

    def unsubscribe(self, queue: ClientQueue) -> None:
        self._clients.discard(queue)

    def broadcast(self, text: str, *, droppable: bool) -> None:
        for client in self._clients:
            client.put(text, droppable=droppable)

    def broadcast_model(self, message: BaseModel) -> None:
        """Send a message to every client (never dropped for slowness)."""
        self.broadcast(message.model_dump_json(), droppable=False)

    async def run(self, source: FanOutSource) -> None:
        """Until cancelled: the telemetry every ``BATCH_PERIOD_S``, the status tick and
        the client counts every ``STATUS_PERIOD_S``."""
        last_status = self._clock()
        while True:
            await asyncio.sleep(BATCH_PERIOD_S)
            for text in source.take_telemetry(bool(self._clients)):
                self.broadcast(text, droppable=True)
            now = self._clock()
            if now - last_status >= STATUS_PERIOD_S:
                last_status = now
                source.status_tick(now)
                for client in self._clients:
                    stats = ClientStats(sent=client.sent, dropped=client.dropped)
                    client.put(stats.model_dump_json(), droppable=True)
