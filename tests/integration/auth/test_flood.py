"""A login flood against the exposed mode: STOP does not wait behind it, and the throttle
holds under concurrency.

The server is a real uvicorn on a recorded simulated SLAP2 line, in exposed mode behind
a "proxy" on 127.0.0.1, so ``X-Forwarded-For`` gives each client its address. STOP is
timed twice per request: its answer, and the ``st`` on the simulated device's own
record of the wire (``WireRecorder``). The baseline is measured in the same test,
before and after the flood, so the comparison does not depend on the machine's speed.
The flood comes from another process, as separate clients would send it.

Passwords at the product's cost (RFC 9106), not the tests' cheap one: what STOP must not
wait behind is real hashing work (an unknown name is checked against a hash at the
app's cost).
"""

from __future__ import annotations

import asyncio
import contextlib
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from servotune.auth.passwords import PRODUCT_PASSWORD_COST
from tests.support.control import WireRecorder, exposed_line_server, session_of
from tests.support.paths import SUPPORT
from tests.support.waiting import wait_for

FLOOD_ADDRESS = "198.51.100.66"
VIEWER_ADDRESS = "192.0.2.5"
ADDRESSES = [0, 1]


async def timed_stop(http: httpx.AsyncClient, wire: WireRecorder) -> tuple[float, float]:
    """(seconds to the answer, seconds until every module had its ``st`` on the wire)."""
    started = time.monotonic()
    response = await http.post("/api/stop")
    answered = time.monotonic() - started
    assert response.status_code == 200, response.text
    deadline = time.monotonic() + 30
    on_wire: list[float] = []
    while time.monotonic() < deadline:
        on_wire = [t for a in ADDRESSES if (t := wire.first("st", a, started)) is not None]
        if len(on_wire) == len(ADDRESSES):
            break
        await asyncio.sleep(0.005)
    assert len(on_wire) == len(ADDRESSES), "STOP never reached the wire"
    return answered, max(on_wire) - started


@dataclass
class Flood:
    """``count`` concurrent logins with unknown names from one address, sent by another
    process (``tests/support/login_flood.py``): the test process only times STOP."""

    base_url: str
    count: int
    statuses: list[int] = field(default_factory=list)
    process: asyncio.subprocess.Process | None = None
    reader: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self.process = await asyncio.create_subprocess_exec(
            sys.executable,
            str(SUPPORT / "login_flood.py"),
            self.base_url,
            str(self.count),
            FLOOD_ADDRESS,
            stdout=asyncio.subprocess.PIPE,
        )
        assert self.process.stdout is not None
        line = await asyncio.wait_for(self.process.stdout.readline(), 30)
        assert line.strip() == b"started", line
        self.reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        async for line in self.process.stdout:
            if line.strip().isdigit():
                self.statuses.append(int(line))

    @property
    def outstanding(self) -> int:
        return self.count - len(self.statuses)

    async def kill(self) -> None:
        if self.process is not None and self.process.returncode is None:
            self.process.kill()
            await self.process.wait()
        if self.reader is not None:
            self.reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, ValueError):
                await self.reader


async def test_stop_is_not_held_by_a_login_flood_and_the_throttle_holds(tmp_path: Path) -> None:
    async with exposed_line_server(
        tmp_path, ADDRESSES, password_cost=PRODUCT_PASSWORD_COST
    ) as server:
        viewer = await session_of(server, "victor", VIEWER_ADDRESS)
        flood = Flood(server.base_url, 100)
        try:
            for address in ADDRESSES:  # the link is up and polling
                await wait_for(
                    lambda a=address: bool(server.wire.since(0, a)), 20, f"module {address} polled"
                )
            baseline = [await timed_stop(viewer, server.wire) for _ in range(5)]
            passwords = server.app.state.security.passwords  # type: ignore[attr-defined]
            checks_before = passwords.checks  # the viewer's own login
            await flood.start()
            during: list[tuple[float, float]] = []
            await asyncio.sleep(0.5)  # every login is in; the first ones are being hashed
            while flood.outstanding > 0 and len(during) < 8:
                before = flood.outstanding
                stop = await timed_stop(viewer, server.wire)
                # Counted only when the flood was still unanswered on both sides of this
                # STOP: a STOP after the flood would prove nothing.
                if before > 0 and flood.outstanding > 0:
                    during.append(stop)
                await asyncio.sleep(0.2)
            statuses = list(flood.statuses)
            # The checks that passed the throttle are queued for the hashing workers; on
            # a loaded machine they take minutes there (their priority is low on
            # purpose). What was let through is counted now: it cannot change.
            checks = passwords.checks - checks_before
            baseline += [await timed_stop(viewer, server.wire) for _ in range(5)]
        finally:
            await viewer.aclose()
            await flood.kill()
    print(f"baseline answer/wire ms: {[(round(a * 1e3), round(w * 1e3)) for a, w in baseline]}")
    print(f"during the flood:        {[(round(a * 1e3), round(w * 1e3)) for a, w in during]}")
    print(f"statuses so far: 429 x {statuses.count(429)}, 401 x {statuses.count(401)}")
    assert len(during) >= 3, "the flood ended before STOP could be timed during it"
    for index, what in ((0, "answer"), (1, "st on the wire")):
        base = statistics.median(s[index] for s in baseline)
        loaded = statistics.median(s[index] for s in during)
        assert loaded <= base + 0.050, (
            f"STOP {what}: median {loaded * 1e3:.0f} ms during the flood against "
            f"{base * 1e3:.0f} ms without it"
        )
    # Never more password checks than the per-address limit, however concurrent: the
    # rest answered 429 at once, unchecked.
    assert checks == 20
    assert statuses.count(429) == 80
    assert set(statuses) <= {401, 429}
