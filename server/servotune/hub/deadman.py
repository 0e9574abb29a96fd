"""The dead-man's judgement: which tabs went silent, which are only late, and why.

A holder (or mover) of an axis renews its lease with heartbeats; ``DeadMan`` tells which
clients' leases ran out (a closed tab, a sleeping laptop, a cut network, a frozen page),
forgives a late one whose connection is demonstrably alive within
``ControlSettings.alive_grace_s``, writes to late tabs so that their machines have
something to acknowledge, and words the reason a lapse gives. It decides nothing about
axes: the control lock (``hub/control_lock.py``) runs the watchdog and lapses.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from servotune.hub.control_client import ControlClient, ControlSettings

# A tab whose heartbeat is this late gets a small message every PROBE_PERIOD_S, so that
# its machine has something to acknowledge by the time its lease runs out.
PROBE_AFTER_S = 0.2
PROBE_PERIOD_S = 0.1
# An acknowledgement counts as "after the last heartbeat" when it came this much later.
ACK_AFTER_HEARTBEAT_S = 0.05


class DeadMan:
    """The judge over ``clients()`` (only those ``responsible`` for an axis: holding or
    having moved one), on ``clock`` and the current ``settings()``."""

    def __init__(
        self,
        settings: Callable[[], ControlSettings],
        clock: Callable[[], float],
        clients: Callable[[], Iterable[ControlClient]],
        responsible: Callable[[ControlClient], bool],
    ) -> None:
        self._settings = settings
        self._clock = clock
        self._clients = clients
        self._responsible = responsible

    def silent_clients(self) -> list[ControlClient]:
        """Clients with axes that went silent (no heartbeat for ``lease_s``: a closed
        tab, a sleeping laptop, a cut network) or whose page froze (its worker still
        beats, the page has not run for ``frozen_page_s``)."""
        now = self._clock()
        deadline = now - self._settings().lease_s
        frozen = self._settings().frozen_page_s
        return [
            c
            for c in list(self._clients())
            if (
                (c.heard_s < deadline and not self.forgiven(c, now))
                or c.page_age_s + now - c.heard_s > frozen
            )
            and not c.lapsing
            and self._responsible(c)
        ]

    def probe_late_clients(self) -> None:
        """Write to every tab whose heartbeat is late (after ``PROBE_AFTER_S``), every
        ``PROBE_PERIOD_S``: by the time its lease runs out its machine has had data to
        acknowledge, or not (``forgiven``)."""
        now = self._clock()
        for client in list(self._clients()):
            if (
                client.probe is not None
                and now - client.heard_s > PROBE_AFTER_S
                and now - client.probed_s >= PROBE_PERIOD_S
                and not client.lapsing
                and self._responsible(client)
            ):
                client.probed_s = now
                client.probe()

    def forgiven(self, client: ControlClient, now: float) -> bool:
        """A late client whose connection is demonstrably alive, within the grace: its
        machine acknowledged data after its last heartbeat arrived (a cut network or a
        sleeping laptop acknowledges nothing from the moment it goes), and within the
        lease (so a cut after that heartbeat is seen within the lease too)."""
        silent_s = now - client.heard_s
        if client.alive is None or silent_s > self._settings().alive_grace_s:
            return False
        checked_at, ack_s = client.alive_cache
        if now - checked_at > 0.05:
            ack_s = client.alive()
            client.alive_cache = (now, ack_s)
            checked_at = now
        if ack_s is None:
            return False
        ack_s += now - checked_at  # as old as it is now
        return ack_s <= min(self._settings().lease_s, silent_s - ACK_AFTER_HEARTBEAT_S)

    def lapse_reason(self, client: ControlClient, now: float) -> str:
        """Why ``client``'s lease lapsed at ``now``, as the user reads it."""
        settings = self._settings()
        silent_ms = round(1000 * (now - client.heard_s))
        if silent_ms <= 1000 * settings.lease_s:
            frozen = client.page_age_s + now - client.heard_s
            return f"the page has not run for {frozen:.1f} s (frozen)"
        source = "its worker" if client.beats else "the page itself"
        why = f"no heartbeat for {silent_ms} ms (from {source}"
        ack_s = client.alive_cache[1]
        grace_s = settings.alive_grace_s
        if client.alive is not None and silent_ms > 1000 * grace_s:
            # Not asked by ``forgiven`` past the grace: ask now, for the message (a live
            # machine past the grace is not "unknown").
            ack_s = client.alive()
        if client.alive is None or ack_s is None:
            return why + "; its connection cannot be checked)"
        why += f"; its machine last acknowledged {1000 * ack_s:.0f} ms ago"
        if silent_ms > 1000 * grace_s:
            why += f", but a live connection is forgiven {grace_s:g} s only"
        return why + ")"
