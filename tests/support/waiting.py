"""Waiting in tests: poll a condition with a deadline; completion order of jobs."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Awaitable, Callable

import pytest


async def wait_for(
    condition: Callable[[], bool], timeout_s: float = 5.0, what: str = "condition"
) -> None:
    """Poll ``condition`` until true; fail the test with ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.02)


async def gather_in_order(*jobs: Awaitable[object]) -> list[int]:
    """Run awaitables concurrently; return their indexes in completion order."""
    order: list[int] = []

    async def run(index: int, job: Awaitable[object]) -> None:
        with contextlib.suppress(Exception):
            await job
        order.append(index)

    await asyncio.gather(*(run(i, j) for i, j in enumerate(jobs)))
    return order
