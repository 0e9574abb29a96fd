"""The soak's and the benchmark's websocket reader (servotune.perf.demo.StreamWatcher):
it connects again after a drop, as the web client does, and keeps the drop."""

from __future__ import annotations

import json
import socket
import threading
import time

from websockets.sync.server import ServerConnection, serve

from servotune.perf.demo import StreamWatcher


def _telemetry(n: int) -> str:
    return json.dumps(
        {"type": "telemetry", "axis": "a", "t": [float(n)], "flags": {}, "channels": {}}
    )


def test_the_watcher_connects_again_after_a_drop_and_keeps_it() -> None:
    connections: list[int] = []

    def handler(ws: ServerConnection) -> None:
        connections.append(1)
        ws.send(_telemetry(len(connections)))
        if len(connections) == 1:
            # The first connection dies without a close frame (a starved server).
            ws.socket.shutdown(socket.SHUT_RDWR)
            return
        time.sleep(1.0)

    with serve(handler, "127.0.0.1", 0) as server:
        port = server.socket.getsockname()[1]
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        with StreamWatcher(f"http://127.0.0.1:{port}") as watcher:
            deadline = time.monotonic() + 10
            while watcher.counts.samples["a"] < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert watcher.counts.samples["a"] == 2
            assert watcher.error is None
            assert len(watcher.drops) == 1
            lost, back, _ = watcher.drops[0]
            assert back is not None and back >= lost
            assert watcher.down_since(lost - 1) and not watcher.down_since(back + 0.001)
        server.shutdown()
