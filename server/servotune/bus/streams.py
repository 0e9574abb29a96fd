"""The lab's JetStream streams and their limits (created and kept up to date by the hub).

* ``SERVOTUNE_RUNS``: finished runs, kept until the hub has stored them: work-queue
  retention (a run is deleted when the hub's consumer acknowledges it, which it does
  after the SQLite write), at most ``runs_max_bytes`` and ``runs_max_age_s``, one run
  at most ``RUN_MAX_BYTES``. Full, it refuses new runs (discard new): a rig keeps an
  unacknowledged run and publishes it again later (``RigAgent._publish_runs``), nothing
  stored only in the stream is ever dropped to make room. ``runs_max_bytes`` is
  reserved on the lab server's JetStream file store (nats-server refuses a stream its
  ``max_file_store`` cannot hold): size both (docs/lab.md).
* ``SERVOTUNE_RIGS``: one manifest per rig (last value), at most ``RIGS_MAX_BYTES``.
* ``SERVOTUNE_PRESENCE``: one presence per rig, memory, ``PRESENCE_TTL_S`` old at most.
  In memory, it is gone when the lab's server restarts: the hub creates it again when
  its connection comes back (``ensure_bus_state`` from the reconnect callback).
"""

from __future__ import annotations

import logging

from nats.aio.client import Client
from nats.js.api import DiscardPolicy, RetentionPolicy, StorageType, StreamConfig
from nats.js.errors import NotFoundError

from servotune.bus import subjects

logger = logging.getLogger(__name__)

RUNS_DUPLICATE_WINDOW_S = 24 * 3600.0
RUNS_MAX_BYTES = 1 << 30
RUNS_MAX_AGE_S = 30 * 24 * 3600.0
# One run with its samples is one message (the servers' max_payload is 8 MB).
RUN_MAX_BYTES = 8 << 20
RIGS_MAX_BYTES = 64 << 20
MANIFEST_MAX_BYTES = 1 << 20
PRESENCE_MAX_BYTES = 1 << 20


def runs_limits(config: StreamConfig, max_bytes: int, max_age_s: float) -> StreamConfig:
    """``config`` with the runs stream's limits and retention (``SERVOTUNE_RUNS``)."""
    config.retention = RetentionPolicy.WORK_QUEUE
    config.discard = DiscardPolicy.NEW
    config.max_bytes = max_bytes
    config.max_age = max_age_s
    config.max_msg_size = RUN_MAX_BYTES
    config.duplicate_window = RUNS_DUPLICATE_WINDOW_S
    return config


def bus_streams(
    runs_max_bytes: int = RUNS_MAX_BYTES, runs_max_age_s: float = RUNS_MAX_AGE_S
) -> list[StreamConfig]:
    """The rigs, presence and runs streams, with their limits."""
    return [
        StreamConfig(
            name=subjects.RIGS_STREAM,
            subjects=[subjects.RIGS_SUBJECTS],
            max_msgs_per_subject=1,
            max_bytes=RIGS_MAX_BYTES,
            max_msg_size=MANIFEST_MAX_BYTES,
            storage=StorageType.FILE,
        ),
        StreamConfig(
            name=subjects.PRESENCE_STREAM,
            subjects=[subjects.PRESENCE_SUBJECTS],
            max_msgs_per_subject=1,
            max_age=subjects.PRESENCE_TTL_S,
            max_bytes=PRESENCE_MAX_BYTES,
            storage=StorageType.MEMORY,
        ),
        runs_limits(
            StreamConfig(
                name=subjects.RUNS_STREAM,
                subjects=[subjects.RUNS_SUBJECTS],
                storage=StorageType.FILE,
            ),
            runs_max_bytes,
            runs_max_age_s,
        ),
    ]


_LIMITS = ("max_bytes", "max_age", "max_msg_size", "discard", "max_msgs_per_subject")


async def ensure_bus_state(
    nc: Client, runs_max_bytes: int = RUNS_MAX_BYTES, runs_max_age_s: float = RUNS_MAX_AGE_S
) -> None:
    """Create the rigs, presence and runs streams if they are missing, and bring the
    limits of existing ones up to date (the hub's job, at start and on reconnect)."""
    js = nc.jetstream()
    for config in bus_streams(runs_max_bytes, runs_max_age_s):
        assert config.name is not None
        try:
            info = await js.stream_info(config.name)
        except NotFoundError:
            await js.add_stream(config=config)
            logger.info("bus: stream %s created", config.name)
            continue
        current = info.config
        if config.retention is not None and current.retention != config.retention:
            logger.warning(
                "bus: stream %s was created with %s retention by an older hub: what the hub "
                "stored stays until the stream's limits remove it; delete it once the hub "
                "has collected every run (docs/lab.md) to have runs removed once stored",
                config.name,
                current.retention,
            )
        changed = [
            name
            for name in _LIMITS
            if getattr(config, name) is not None and getattr(current, name) != getattr(config, name)
        ]
        if changed:
            for name in changed:
                setattr(current, name, getattr(config, name))
            await js.update_stream(config=current)
            logger.info("bus: stream %s limits updated (%s)", config.name, ", ".join(changed))
