"""How servotune connects to the bus: URL, credentials from a file, names.

Credentials never come from the command line or the environment's process listing:
``--bus-credentials FILE`` names either a NATS ``.creds`` file (JWT + nkey seed, for a
decentralised-auth lab) or a two-line text file with the user name on the first line
and the password on the second. Neither is logged.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import nats
from nats.aio.client import Client
from nats.errors import SlowConsumerError

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
    # A rig only: ``url`` is the rig's own nats-server, a leaf node of the lab's, with
    # JetStream in domain ``<rig>`` (``bus.leaf``): the rig's manifest and runs are kept
    # in streams there, and the lab's streams source them.
    leaf: bool = False
    # How often presence and keep-alives go out, and when silence means offline.
    presence_period_s: float = 0.5
    offline_after_s: float = 1.5
    keepalive_period_s: float = 0.1
    request_timeout_s: float = 5.0
    stop_timeout_s: float = 2.0
    # A command the rig has not taken this long after the hub sent it is not run (the
    # rig drops it: ``CommandRequest.deadline_s``); the hub says so a second later.
    command_start_within_s: float = 3.0
    # The hub takes at most this much telemetry a second from one rig (``bus.gate``):
    # about 5,000 SLAP2 samples/s in 30 batches/s per axis; more sheds that rig's oldest.
    rig_telemetry_bytes_per_s: float = 500_000.0


HubRole = Literal["operate", "view", "stop"]
# The hub's NATS users besides its operating one (``accounts.hub_users``): the file of
# each sits next to the hub's own, named after it (``hub.cred`` -> ``hub-view.cred``).
ROLE_SUFFIX: dict[HubRole, str] = {"operate": "", "view": "-view", "stop": "-stop"}


def role_credentials(path: Path, role: HubRole) -> Path:
    """The credential file of the hub's ``role`` user, next to the hub's ``path``."""
    return path.with_name(f"{path.stem}{ROLE_SUFFIX[role]}{path.suffix}")


def role_settings(settings: BusSettings, role: HubRole) -> BusSettings:
    """``settings`` with the credentials of the hub's ``role`` connection.

    Each of the hub's connections is its own NATS user, so nats-server itself limits
    what each may send (a ``view`` connection cannot publish a command). A lab without
    those users (no file next to the hub's) runs every connection as the hub's user,
    with a warning: then only the hub's own checks separate them.
    """
    if settings.credentials is None or role == "operate":
        return settings
    path = role_credentials(settings.credentials, role)
    if not path.exists():
        logger.warning(
            "bus: no %s next to %s: the hub's %s connection uses the hub's own user",
            path.name,
            settings.credentials.name,
            role,
        )
        return settings
    return replace(settings, credentials=path)


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
    on_reconnect: Callable[[], Awaitable[None]] | None = None,
) -> Client:
    """A connection to the bus that reconnects for ever (a rig outlives lab outages).
    ``on_reconnect``: called after every reconnection."""
    # What nats-py reports again and again (a message dropped for a slow consumer, a
    # reconnect attempt refused) is counted and logged at most every 10 s per kind.
    repeated: dict[str, list[float]] = {}

    async def error_cb(exc: Exception) -> None:
        # nats-py reports permission violations and lost connections here; the message
        # names the subject, never a credential.
        kind = type(exc).__name__
        if isinstance(exc, SlowConsumerError | OSError):
            seen = repeated.setdefault(kind, [0.0, -60.0])
            seen[0] += 1
            if time.monotonic() - seen[1] < 10.0:
                return
            seen[1] = time.monotonic()
            logger.warning("bus %s: %s (%d times so far)", name, exc, int(seen[0]))
        else:
            logger.warning("bus %s: %s", name, exc)
        if on_error is not None:
            await on_error(exc)

    async def reconnected_cb() -> None:
        logger.info("bus %s: connected again", name)
        if on_reconnect is not None:
            await on_reconnect()

    options: dict[str, Any] = {
        "servers": [settings.url],
        "name": name,
        "error_cb": error_cb,
        "reconnected_cb": reconnected_cb,
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
