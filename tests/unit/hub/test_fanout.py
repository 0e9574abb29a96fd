"""Per-client queues: a slow client loses old telemetry, never state changes."""

from __future__ import annotations

import asyncio

from servotune.hub.state import ClientQueue


async def test_full_queue_drops_oldest_telemetry_and_keeps_status() -> None:
    queue = ClientQueue(max_messages=4)
    queue.put("status-1", droppable=False)
    for index in range(10):
        queue.put(f"telemetry-{index}", droppable=True)
    queue.put("status-2", droppable=False)
    received = [await queue.get() for _ in range(len(queue))]
    assert received[0] == "status-1"
    assert received[-1] == "status-2"
    assert [m for m in received if m.startswith("telemetry")] == ["telemetry-8", "telemetry-9"]
    assert queue.dropped == 8
    assert queue.sent == 4


async def test_get_waits_for_the_next_message() -> None:
    queue = ClientQueue()
    waiter = asyncio.create_task(queue.get())
    await asyncio.sleep(0.01)
    assert not waiter.done()
    queue.put("hello", droppable=False)
    assert await asyncio.wait_for(waiter, 1) == "hello"
