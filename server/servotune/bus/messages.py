"""The bus payloads, schema v1. Telemetry, status, parameters and events travel as the
websocket's own ``servotune.wire`` models; these are what the bus adds around them.

A change of this schema bumps ``SCHEMA`` and the subject prefix (``subjects.PREFIX``).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from servotune.descriptor import DeviceDescriptor
from servotune.wire import AxisInfo, LinkInfo

SCHEMA = 1


class RemoteAxisInfo(BaseModel):
    info: AxisInfo
    descriptor: DeviceDescriptor
    # The bench tests the rig runs on this axis (``testbench.TestBench.kinds``).
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
    user's permission; the rig grants a hub session at most an operator's."""

    session: str = Field(min_length=8, max_length=64)
    hub: str = Field(min_length=1, max_length=64)
    values: dict[str, object] = Field(default_factory=dict)
    args: dict[str, object] = Field(default_factory=dict)


ErrorKind = Literal[
    "invalid", "refused", "locked", "forbidden", "link_down", "timeout", "protocol", "device"
]


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
