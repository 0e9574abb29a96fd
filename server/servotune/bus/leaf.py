"""A rig's own nats-server as a leaf node of the lab's: JetStream domains and sourcing.

nats-server 2.9 does not extend the lab's JetStream to a leaf node's clients ("JetStream
Not Extended, adding deny [$JS.API.> $KV.> $OBJ.>]" in both servers' logs when the leaf
connects): a rig behind its leaf cannot publish into the lab's streams. The documented
way, and what works here (``tests/integration/bus/test_leaf.py``, nats-server 2.9.10):

* the rig's server runs JetStream in a domain of its own, named after the rig
  (``jetstream { domain: rig-1 }``), and keeps the rig's runs in a stream there,
  ``SERVOTUNE_RUNS_<rig>`` (``rig_runs_config``): a run is acknowledged by the rig's
  own server, so recording on the rig never waits for the lab network;
* the lab's ``SERVOTUNE_RUNS`` *sources* each rig's stream through that domain's API
  prefix (``$JS.<rig>.API``, ``runs_source``): the lab's server pulls what it has not
  got yet whenever the leaf link is up, so runs recorded while the lab network was down
  arrive when it is back (JetStream, not a home-made resend);
* the rig's leaf user on the lab's server needs, beyond its own subtree, the sourcing
  traffic (``accounts.rig_permissions(..., leaf=True)``): the lab's server sends the
  rig's domain API requests (``$JS.<rig>.API.>``, and flow control ``$JS.FC.>``) into
  the leaf, and the leaf answers on ``$JSC.>`` and delivers on ``$JS.S.>``. Found by
  removing one permission at a time: without ``$JSC.>`` or ``$JS.S.>`` the source
  never becomes active (``active: -1``) and nothing is logged.
"""

from __future__ import annotations

from pathlib import Path

from nats.aio.client import Client
from nats.js.api import DiscardPolicy, ExternalStream, StorageType, StreamConfig, StreamSource
from nats.js.errors import NotFoundError

from servotune.bus import subjects
from servotune.bus.streams import (
    MANIFEST_MAX_BYTES,
    RUN_MAX_BYTES,
    RUNS_DUPLICATE_WINDOW_S,
    RUNS_MAX_AGE_S,
    RUNS_MAX_BYTES,
    runs_limits,
)

# The rig's own runs stream is a buffer for the lab network's outages: the lab's
# stream copies every run as soon as the leaf link is up. Its oldest runs go first
# when it is full or a week old (the rig's own store keeps every run anyway): size it
# for the longest outage of the lab network (docs/lab.md).
RIG_RUNS_MAX_BYTES = 1 << 30
RIG_RUNS_MAX_AGE_S = 7 * 24 * 3600.0


def rig_runs_stream(rig: str) -> str:
    """The rig's runs stream in its own JetStream domain."""
    return f"{subjects.RUNS_STREAM}_{subjects.check_token('rig', rig)}"


def rig_runs_config(rig: str) -> StreamConfig:
    """``SERVOTUNE_RUNS_<rig>`` on the rig's server: its runs, for the lab to copy
    (deduplicated by ``Nats-Msg-Id`` like the lab's; limits: ``RIG_RUNS_MAX_*``)."""
    return StreamConfig(
        name=rig_runs_stream(rig),
        subjects=[subjects.runs(rig)],
        storage=StorageType.FILE,
        duplicate_window=RUNS_DUPLICATE_WINDOW_S,
        max_bytes=RIG_RUNS_MAX_BYTES,
        max_age=RIG_RUNS_MAX_AGE_S,
        max_msg_size=RUN_MAX_BYTES,
        discard=DiscardPolicy.OLD,
    )


def rig_manifest_stream(rig: str) -> str:
    return f"{subjects.RIGS_STREAM}_{subjects.check_token('rig', rig)}"


def rig_stream_configs(rig: str) -> list[StreamConfig]:
    """The rig's streams on its own server: its manifest (last value) and its runs."""
    return [
        StreamConfig(
            name=rig_manifest_stream(rig),
            subjects=[subjects.manifest(rig)],
            max_msgs_per_subject=1,
            max_bytes=4 * MANIFEST_MAX_BYTES,
            max_msg_size=MANIFEST_MAX_BYTES,
            storage=StorageType.FILE,
        ),
        rig_runs_config(rig),
    ]


async def ensure_rig_streams(nc: Client, rig: str) -> None:
    """The rig agent, on its leaf node: create its streams if they are missing."""
    js = nc.jetstream()
    for config in rig_stream_configs(rig):
        assert config.name is not None
        try:
            await js.stream_info(config.name)
        except NotFoundError:
            await js.add_stream(config=config)


async def ensure_sources(nc: Client, rig: str, domain: str) -> bool:
    """The hub: the lab's rigs and runs streams source the leaf rig's (idempotent);
    True if a source was added."""
    js = nc.jetstream()
    added = False
    for lab_stream, rig_stream in (
        (subjects.RIGS_STREAM, rig_manifest_stream(rig)),
        (subjects.RUNS_STREAM, rig_runs_stream(rig)),
    ):
        info = await js.stream_info(lab_stream)
        config = info.config
        sources = list(config.sources or [])
        if any(s.name == rig_stream for s in sources):
            continue
        sources.append(
            StreamSource(name=rig_stream, external=ExternalStream(api=f"$JS.{domain}.API"))
        )
        config.sources = sources
        await js.update_stream(config=config)
        added = True
    return added


def runs_source(rig: str) -> StreamSource:
    """The lab's ``SERVOTUNE_RUNS`` sources this rig's stream through its domain."""
    return StreamSource(name=rig_runs_stream(rig), external=ExternalStream(api=f"$JS.{rig}.API"))


def lab_runs_config(rigs: list[str]) -> StreamConfig:
    """The lab's runs stream when every rig is a leaf node: no subjects of its own (a
    rig's run reaches it only through its source, never twice); the limits and
    retention of ``bus.streams``."""
    return runs_limits(
        StreamConfig(
            name=subjects.RUNS_STREAM,
            storage=StorageType.FILE,
            sources=[runs_source(rig) for rig in rigs],
        ),
        RUNS_MAX_BYTES,
        RUNS_MAX_AGE_S,
    )


def leaf_node_conf(
    rig: str,
    *,
    port: int,
    store_dir: Path,
    lab_leaf_url: str,
    credentials_file: Path,
    host: str = "127.0.0.1",
) -> str:
    """The rig PC's nats-server configuration: JetStream in the rig's own domain, one
    local account for the rig's servotune, a leaf link to the lab with the rig's user.

    ``credentials_file``: the rig's ``.cred`` file of ``servotune bus-accounts`` (user,
    password); the password goes into this configuration (mode 0600, like the file),
    never on a command line. ``lab_leaf_url``: ``nats-leaf://lab-nats:7422``."""
    subjects.check_token("rig", rig)
    user, password = credentials_file.read_text().splitlines()[:2]
    host_part = lab_leaf_url.split("://", 1)[-1]
    return f"""# Written for rig {rig}: its own nats-server, a leaf node of the lab's (docs/lab.md).
server_name: {rig}
listen: {host}:{port}
# A run with its samples is one message (as on the lab's server).
max_payload: 8MB
# The rig's runs stream reserves 1 GB of it (servotune.bus.leaf.RIG_RUNS_MAX_BYTES).
jetstream {{ store_dir: "{store_dir}", domain: {rig}, max_file_store: 2GB, max_memory_store: 64MB }}
accounts {{
  RIG {{ jetstream: enabled, users: [ {{ user: "{rig}", password: "{password}" }} ] }}
}}
leafnodes {{
  remotes: [ {{ url: "nats-leaf://{user}:{password}@{host_part}", account: RIG }} ]
}}
"""
