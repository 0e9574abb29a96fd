"""Host CPU per SLAP2 exchange through the serial channel's receive path, without a pty.

    PYTHONPATH=server .venv/bin/python scripts/perf_channel_cpu.py [exchanges] [repeats]

A fake transport answers every byte written with its echo (and ``-1234`` CR after a
CR) from the event loop, so only the channel (``SerialChannel.drive``), the SLAP2 echo
handler (``EchoLine``/``EchoExchange``) and the loop run: CPU time per ``rp`` exchange,
plain and with the next read chained, best of ``repeats``. CPU time, not wall time: far
less sensitive to a loaded host than the wire benchmarks (``servotune perf slap2``,
``scripts/perf_capture.py``), for comparing two versions of that path.
"""

from __future__ import annotations

import asyncio
import sys
import time
from collections.abc import Callable, Coroutine
from typing import Any

from servotune.devices.slap2.echo import EchoLine
from servotune.transports import serial


class _AnsweringTransport(asyncio.Transport):
    def __init__(self, protocol: asyncio.Protocol, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__()
        self._protocol, self._loop = protocol, loop

    def write(self, data: bytes | bytearray | memoryview) -> None:
        out = bytes(data)
        if out.endswith(b"\r"):
            out += b"-1234\r"
        self._loop.call_soon(self._protocol.data_received, out)

    def close(self) -> None:
        pass

    def is_closing(self) -> bool:
        return False


async def main(exchanges: int, repeats: int) -> None:
    loop = asyncio.get_running_loop()
    protocol = serial._SerialProtocol()
    transport = _AnsweringTransport(protocol, loop)
    protocol.connection_made(transport)
    line = EchoLine(serial.SerialChannel(transport, protocol, "fake"))

    async def one(then: bytes) -> None:
        done = await line.transact(b"rp\r", 0x0D, 0.5, 0.5, then=then)
        assert done.reply == b"-1234\r", done

    for name, then in (("plain", b""), ("chained", b"rp\r")):
        best_s = float("inf")
        for _ in range(repeats):
            started = time.process_time()
            for _ in range(exchanges):
                await one(then)
            best_s = min(best_s, (time.process_time() - started) / exchanges)
        print(f"{name}: {best_s * 1e6:.2f} us CPU per exchange (best of {repeats})")


if __name__ == "__main__":
    try:
        import uvloop

        runner: Callable[[Coroutine[Any, Any, None]], None] = uvloop.run
    except ImportError:
        runner = asyncio.run
    given = [int(x) for x in sys.argv[1:3]]
    runner(main(*given, *(5000, 5)[len(given) :]))
