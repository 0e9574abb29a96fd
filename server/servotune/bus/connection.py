"""How servotune connects to the bus: URL, credentials from a file, names.

Credentials never come from the command line or the environment's process listing:
``--bus-credentials FILE`` names either a NATS ``.creds`` file (JWT + nkey seed, for a
decentralised-auth lab) or a two-line text file with the user name on the first line
and the password on the second. Neither is logged.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import nats
from nats.aio.client import Client

logger = logging.getLogger(__name__)


class BusConfigError(ValueError):
    """A bus setting that cannot be used; the message names the option."""


@dataclass(frozen=True, slots=True)
class BusSettings:
    """``url``: the nats-server (on a rig: its own leaf node). ``rig``: this server is a
    rig of that name; ``hub``: this server is the lab's central dashboard."""

    url: str
    rig: str | None = None
    hub: str | None = None
    credentials: Path | None = None
    # How often presence and keep-alives go out, and when silence means offline.
    presence_period_s: float = 0.5
    offline_after_s: float = 1.5
    keepalive_period_s: float = 0.1
    request_timeout_s: float = 5.0
    stop_timeout_s: float = 2.0


def _credential_options(path: Path | None) -> dict[str, Any]:
    if path is None:
        return {}
    if path.suffix == ".creds":
        return {"user_credentials": str(path)}
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise BusConfigError(f"--bus-credentials: cannot read {path}: {exc.strerror}") from None
    if len(lines) < 2 or not lines[0].strip() or not lines[1]:
        raise BusConfigError(
            f"--bus-credentials: {path} must hold the user name on line 1 and the password "
            "on line 2 (or be a .creds file)"
        )
    return {"user": lines[0].strip(), "password": lines[1]}


async def connect_bus(
    settings: BusSettings,
    *,
    name: str,
    inbox_prefix: str | None = None,
    on_error: Callable[[Exception], Awaitable[None]] | None = None,
) -> Client:
    """A connection to the bus that reconnects for ever (a rig outlives lab outages)."""

    async def error_cb(exc: Exception) -> None:
        # nats-py reports permission violations and lost connections here; the message
        # names the subject, never a credential.
        logger.warning("bus %s: %s", name, exc)
        if on_error is not None:
            await on_error(exc)

    options: dict[str, Any] = {
        "servers": [settings.url],
        "name": name,
        "error_cb": error_cb,
        "allow_reconnect": True,
        "max_reconnect_attempts": -1,
        "reconnect_time_wait": 0.5,
        "connect_timeout": 2,
        "ping_interval": 5,
        "max_outstanding_pings": 2,
        **_credential_options(settings.credentials),
    }
    if inbox_prefix is not None:
        options["inbox_prefix"] = inbox_prefix
    client: Client = await nats.connect(**options)
    return client
