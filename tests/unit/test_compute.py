"""The compute worker (servotune.compute): results and exceptions come back as from a
call, the work runs in another process, a dead worker is replaced, close ends it."""

from __future__ import annotations

import os
import signal

import pytest

from servotune.compute import ComputePool


def _pid_and_sum(values: list[int], *, offset: int = 0) -> tuple[int, int]:
    return os.getpid(), sum(values) + offset


def _refuse(field: str) -> None:
    raise ValueError(f"{field} out of range")


async def test_a_call_runs_in_a_worker_process_and_its_errors_come_back() -> None:
    pool = ComputePool(preload=())
    try:
        pid, total = await pool.run(_pid_and_sum, [1, 2, 3], offset=10)
        assert total == 16 and pid != os.getpid()
        with pytest.raises(ValueError, match="max_pwm out of range"):
            await pool.run(_refuse, "max_pwm")
        # The worker stays for the next call.
        assert (await pool.run(_pid_and_sum, []))[0] == pid
    finally:
        await pool.close()
    with pytest.raises(RuntimeError, match="closed"):
        await pool.run(_pid_and_sum, [])


async def test_a_worker_that_died_is_replaced_and_the_call_made_again() -> None:
    pool = ComputePool(preload=())
    try:
        pid, _ = await pool.run(_pid_and_sum, [])
        os.kill(pid, signal.SIGKILL)
        new_pid, total = await pool.run(_pid_and_sum, [4, 5])
        assert total == 9 and new_pid not in (pid, os.getpid())
    finally:
        await pool.close()
