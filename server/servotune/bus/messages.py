"""The bus payloads, schema v1. Telemetry, status, parameters and events travel as the
websocket's own ``servotune.schema`` models; these are what the bus adds around them.

A change of this schema bumps ``SCHEMA`` and the subject prefix (``subjects.PREFIX``).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from servotune.descriptor import DeviceDescriptor
from servotune.schema import AxisInfo, LinkInfo

SCHEMA = 1


class RemoteAxisInfo(BaseModel):
    info: AxisInfo
    descriptor: DeviceDescriptor
    # The bench tests the rig runs on this axis (``bench.service.TestBench.kinds``).
    bench_kinds: list[str] = Field(default_factory=list)


class RemoteLinkInfo(BaseModel):
    info: LinkInfo
    axes: list[RemoteAxisInfo]


class RigManifest(BaseModel):
    """What a rig offers (key ``<rig>`` of ``servotune_rigs``); written at start-up."""

    schema_version: int = SCHEMA
    rig: str
    server_version: str
    links: list[RemoteLinkInfo]
    # The JetStream domain of the rig's own nats-server (a leaf node), None: the lab's.
    domain: str | None = None


class Presence(BaseModel):
    """Key ``<rig>`` of ``servotune_presence``, rewritten every ``period_s``."""

    rig: str
    period_s: float
    sent_wall_s: float


class CommandRequest(BaseModel):
    """Body of ``...<axis>.cmd.<verb>``: which hub session asks (its keep-alive is the
    rig's dead-man for what it moves) and the arguments. The hub has checked its own
    user's permission; the rig grants a hub session at most an operator's.

    Times are on the rig's clock (its server's ``Hub.now()``), converted by the hub
    from its round-trip estimate of that clock (``bus.clock``), each rounded the
    safe way: ``deadline_s`` the latest the rig may start the command (a request that
    comes later is dropped and reported, never run: the hub has told its user it
    failed); ``reply_by_s`` when the hub stops waiting for the outcome; ``pressed_s``
    (STOP only) when the user pressed it: a STOP pressed before the axis was
    commanded or stopped again is not sent (it must not act on motion started after
    it). Every verb but STOP and the reads needs a deadline."""

    session: str = Field(min_length=8, max_length=64)
    hub: str = Field(min_length=1, max_length=64)
    values: dict[str, object] = Field(default_factory=dict)
    args: dict[str, object] = Field(default_factory=dict)
    sent_s: float | None = None
    deadline_s: float | None = None
    reply_by_s: float | None = None
    pressed_s: float | None = None


ErrorKind = Literal[
    "invalid",
    "refused",
    "locked",
    "forbidden",
    "link_down",
    "timeout",
    "protocol",
    "device",
    # Not run: the request came after its deadline / from a hub session the rig's
    # dead-man ended / (STOP) the axis was commanded or stopped after it was pressed.
    "expired",
    "session_ended",
    "overtaken",
]
# Header of the rig's first answer to a request: taken, it runs (its outcome follows).
ACK_HEADER = "St-Taken"


class CommandReply(BaseModel):
    """The rig's answer: ``ok`` with the result, or the error as the rig's REST would
    give it (``kind`` maps to the status code, ``field`` names the bad field)."""

    ok: bool
    result: dict[str, object] = Field(default_factory=dict)
    kind: ErrorKind | None = None
    field: str | None = None
    detail: str = ""


class KeepAlive(BaseModel):
    """Body of ``servotune.v1.<rig>.cmd.keepalive``: the hub session is alive."""

    session: str = Field(min_length=8, max_length=64)
    hub: str = Field(min_length=1, max_length=64)


class RunRecord(BaseModel):
    """A finished run of a rig (the runs stream): its row and its sample rows."""

    rig: str
    run: dict[str, object]
    axis_key: str
    samples: list[list[object]]
