"""``ProcessMaster``'s transport to the simulator process, without a simulator: a
socket that accepts and then stays silent, or answers as told."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from servotune.devices.ep7047.sim.process import ProcessMaster
from servotune.transports.ethercat import EthercatMailboxError


class _Listener:
    """A SOCK_SEQPACKET server at ``path`` that keeps what it receives and answers each
    message with ``reply(message)`` (None: no answer)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.received: list[bytes] = []
        self.reply: dict[bytes, bytes] = {}
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._sock.bind(str(path))
        self._sock.listen(1)
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        try:
            client, _ = self._sock.accept()
        except OSError:
            return
        with client:
            while True:
                try:
                    message = client.recv(1 << 16)
                except OSError:
                    return
                if not message:
                    return
                self.received.append(message)
                answer = self.reply.get(message[:1])
                if answer is not None:
                    client.send(answer)

    def close(self) -> None:
        self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()
        self._thread.join(2)


@pytest.fixture
def listener(tmp_path: Path) -> Iterator[_Listener]:
    server = _Listener(tmp_path / "slave.sock")
    try:
        yield server
    finally:
        server.close()


def test_a_silent_simulator_is_a_mailbox_error_after_the_reply_timeout(
    listener: _Listener,
) -> None:
    master = ProcessMaster(str(listener.path), reply_timeout_s=0.2)
    started = time.monotonic()
    with pytest.raises(EthercatMailboxError, match=r"did not answer within 0\.2 s"):
        master.open("sim")
    waited_s = time.monotonic() - started
    # The kernel's receive timeout ended the wait: not before it, and not never.
    assert waited_s >= 0.19
    assert listener.received and listener.received[0].startswith(b"J")
    # The connection was dropped: the next call reconnects (and fails the same way).
    assert master._sock is None


def test_the_connected_socket_is_blocking_with_the_timeout_in_the_kernel(
    listener: _Listener,
) -> None:
    listener.reply[b"J"] = b'J{"ok": null, "slaves": []}'
    master = ProcessMaster(str(listener.path), reply_timeout_s=0.25)
    master.open("sim")
    try:
        sock = master._sock
        assert sock is not None
        # No Python-level timeout: send and recv are one syscall each, no poll() first.
        assert sock.gettimeout() is None
        raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, 16)
        seconds, micros = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:], "little")
        # The kernel keeps it in scheduler ticks (rounded up to one, a few ms).
        assert 0.25 <= seconds + micros / 1e6 < 0.27
    finally:
        master.close()
