"""Is the far end of a websocket demonstrably alive? Asked of the kernel, not of the page.

The dead-man (``servotune.hub.control_lock``) must stop the axes of a tab that vanished (closed,
a laptop asleep, a network cut) within 500 ms, but must not fire on a live tab whose
browser is starved of CPU and sends its heartbeats late. What tells them apart is the
client machine's TCP stack: the server streams telemetry to every tab about 30 times a
second, and the client's kernel acknowledges it within milliseconds however busy its
browser is; a sleeping laptop or a cut network acknowledges nothing, a closed tab
closes the connection. ``last_ack_s`` reads from Linux's ``TCP_INFO`` of the connection how long
ago the last acknowledgement came; elsewhere, or when the connection cannot be found,
it says None (no evidence: the dead-man keeps its strict lease).

Only meaningful when the TCP peer is the browser's machine itself: behind a reverse
proxy the proxy acknowledges, so the caller does not ask then.
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import sys

# struct tcp_info (linux/tcp.h): 8 single bytes, then 32-bit fields; tcpi_unacked is the
# 5th of those (after rto, ato, snd_mss, rcv_mss), tcpi_last_ack_recv the 13th.
_TCP_INFO = struct.Struct("8B13I")
_UNACKED = 8 + 4
_LAST_ACK_RECV = 8 + 12


def _find(local: tuple[str, int], peer: tuple[str, int]) -> tuple[int, int] | None:
    """(tcpi_unacked, tcpi_last_ack_recv in ms) of this process's TCP connection from
    ``local`` to ``peer``, or None."""
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return None
    for name in fds:
        fd = int(name)
        try:
            if not os.readlink(f"/proc/self/fd/{fd}").startswith("socket:"):
                continue
            sock = socket.socket(fileno=os.dup(fd))
        except OSError:
            continue
        with contextlib.closing(sock):
            try:
                if sock.type != socket.SOCK_STREAM:
                    continue
                if sock.getsockname()[:2] != local or sock.getpeername()[:2] != peer:
                    continue
                data = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, _TCP_INFO.size)
            except OSError:
                continue
        fields = _TCP_INFO.unpack_from(data.ljust(_TCP_INFO.size, b"\0"))
        return fields[_UNACKED], fields[_LAST_ACK_RECV]
    return None


def last_ack_s(local: tuple[str, int], peer: tuple[str, int]) -> float | None:
    """How long ago the peer's kernel last acknowledged data of this process's connection
    from ``local`` to ``peer``, in seconds; None when it cannot be told (not Linux, the
    connection not found). Cheap enough for a rare question (a late heartbeat): a look
    at this process's open sockets. A line the server has not written to lately proves
    nothing (no ack was due): the caller keeps writing to it while it asks
    (``ControlClient.probe``)."""
    if not sys.platform.startswith("linux"):
        return None
    found = _find(local, peer)
    if found is None:
        return None
    _unacked, last_ack_ms = found
    return last_ack_ms / 1000
