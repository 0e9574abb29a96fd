"""What the control lock knows of a browser tab, and the lock's timings.

``ControlClient`` is one websocket connection as the lock (``hub/control_lock.py``) and
the dead-man (``hub/deadman.py``) see it; ``ControlSettings`` their timings;
``AuditSink`` where their decisions are recorded. The api and the lab bus build and
pass these; they hold no behaviour of the lock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from servotune.auth.principal import Principal

CLIENT_HEADER = "X-Servotune-Client"


@dataclass(frozen=True, slots=True)
class ControlSettings:
    """Timings of the lock and the dead-man (tests shorten the hand-over ones).

    ``lease_s`` + ``watchdog_period_s`` + the time of the device's STOP on its wire is
    the dead-man's worst case after the last heartbeat: 350 + 25 + a few ms (target:
    500 ms). The client sends a heartbeat every ``heartbeat_period_s`` (100 ms), so a
    browser on a loaded machine may be up to 250 ms late before its lease lapses.
    """

    heartbeat_period_s: float = 0.1
    lease_s: float = 0.35
    # A page that holds a jog and whose own thread has not run for this long (its
    # heartbeat worker says so) loses its axes too: a frozen page cannot release the jog
    # (docs/control.md). Without a jog held the worker reports no page age.
    frozen_page_s: float = 2.0
    # Heartbeats late beyond the lease are forgiven this long while the tab's connection
    # is demonstrably alive (its machine's TCP stack acknowledges the telemetry: a busy
    # browser, not a vanished one; ``api.tcp_alive``).
    alive_grace_s: float = 2.0
    watchdog_period_s: float = 0.025
    request_timeout_s: float = 30.0
    idle_grant_s: float = 60.0
    autopilot_resume_s: float = 20.0
    stop_timeout_s: float = 2.0
    startup_wait_s: float = 3.0


class AuditSink(Protocol):
    """``servotune.auth.audit``'s ``record`` (set as ``app.state.audit`` by the auth code)."""

    def record(
        self,
        *,
        who: str,
        action: str,
        axis: str | None = None,
        address: str | None = None,
        before: object = None,
        after: object = None,
        result: str = "ok",
        detail: str = "",
    ) -> None: ...


@dataclass(eq=False, slots=True)
class ControlClient:
    """One websocket connection. ``client_id`` is its secret (only it learns it, in
    ``welcome``); ``tag`` is its public name in ``control_status``."""

    client_id: str
    tag: str
    principal: Principal
    address: str
    send: Callable[[str], None]
    # When the server last heard from the client (heartbeat, or a change / hold), and how
    # long the page's own thread had not run by then (its heartbeat worker's report).
    heard_s: float = 0.0
    page_age_s: float = 0.0
    # The longest the server went without hearing from the client while it held or
    # moved an axis (how near its lease came to lapsing); logged when it grows.
    worst_gap_s: float = 0.0
    held_when_heard: bool = False
    lapsing: bool = False
    connected: bool = True
    beats: int = 0  # heartbeats on the worker's socket (0: the page sends its own)
    heartbeats: int = 0  # every heartbeat heard, from the page or its worker
    # How long ago the tab's machine last acknowledged this connection's data (None:
    # cannot be told, e.g. behind a reverse proxy): see ControlSettings.alive_grace_s.
    alive: Callable[[], float | None] | None = None
    alive_cache: tuple[float, float | None] = (-math.inf, None)
    # Sends the tab something small, so that its machine has something to acknowledge
    # while its heartbeats are late (``alive`` needs a busy line to prove anything).
    probe: Callable[[], None] | None = None
    probed_s: float = -math.inf

    @property
    def user(self) -> str:
        return self.principal.user
