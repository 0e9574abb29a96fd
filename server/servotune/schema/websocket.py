"""The websocket ``/ws`` stream: every message has an explicit ``type`` field (not
derived from a class name), so the client can switch on it.

Server -> client: ``hello`` once on connect, then ``telemetry`` batches (about 30 per
second per axis), ``link_status`` and ``axis_status`` when they change (and every
second), ``params`` after every read or write of device parameters, ``event`` for
things a user should see in the log (stops, refusals, resets), ``storage_status`` when
saving fails or works again, ``client_stats`` every second, ``run`` as bench runs
record, ``move_outcome`` when a user's move ends.
Client -> server: ``ping`` (answered by ``client_stats``). Commands go over REST; the
control lock's messages are in ``servotune.schema.control_lock``.

Times ``t`` are seconds on the server's monotonic clock since the server started.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, Field

LinkState = Literal["connecting", "connected", "reconnecting", "error", "disconnected"]
# capture: "paused" while another axis of the link is captured (docs/capture.md)
AxisHealth = Literal["ok", "reset", "offline", "paused"]
EventLevel = Literal["info", "warning", "error"]


class AxisInfo(BaseModel):
    """One axis as listed by ``GET /api/axes``."""

    id: str
    device: str
    link: str
    address: int
    name: str


class LinkInfo(BaseModel):
    id: str
    device: str
    path: str
    baud: int


class Hello(BaseModel):
    type: Literal["hello"] = "hello"
    server_version: str
    axes: list[AxisInfo]
    links: list[LinkInfo]
    autopilot: bool


class Telemetry(BaseModel):
    """A batch of samples of one axis, oldest first; all lists have the length of ``t``.

    ``channels`` maps a descriptor channel name to values in device units (``null``
    where a slower channel has no sample at that time);
    ``flags`` maps a descriptor flag name to 0/1 per sample.
    """

    type: Literal["telemetry"] = "telemetry"
    axis: str
    t: list[float]
    channels: dict[str, list[float | None]]
    flags: dict[str, list[int]]


class LinkStatus(BaseModel):
    type: Literal["link_status"] = "link_status"
    link: str
    state: LinkState
    message: str
    rate_hz: float = Field(description="telemetry samples per second per axis, achieved")
    wire_limit_hz: float = Field(description="what the wire allows for the same poll set")
    wire_busy: float | None = Field(
        default=None,
        description=(
            "share (0..1) of the last 2 s the line carried this link's exchanges (polls, "
            "commands and echoes alike); null where not measured (EtherCAT: cyclic, "
            "rate_hz / wire_limit_hz says it) or while no channel is open"
        ),
    )
    errors: int
    counters: dict[str, int] = Field(
        default_factory=dict,
        description=(
            "what the link retried, resynchronised or dropped since start instead of "
            "alarming (retries, desyncs, dropped_bytes, restarts; EP7047: lost_frames, "
            "overruns, watchdog_trips; Z1100: fence_timeouts)"
        ),
    )


class AxisStatus(BaseModel):
    type: Literal["axis_status"] = "axis_status"
    axis: str
    health: AxisHealth
    message: str
    operated: bool = Field(description="a user has operated this axis (autopilot is off)")


class Params(BaseModel):
    type: Literal["params"] = "params"
    axis: str
    values: dict[str, int]
    source: Literal["read", "write", "restore", "stored"] = Field(
        description="stored: the values the device's save command stored (non-volatile), "
        "as far as servotune saw it save them"
    )


class Event(BaseModel):
    type: Literal["event"] = "event"
    t: float
    level: EventLevel
    axis: str | None
    message: str


class RunUpdate(BaseModel):
    """Progress of a bench run: every browser sees runs appear, record and finish."""

    type: Literal["run"] = "run"
    axis: str
    run_id: str
    status: Literal["recording", "complete", "incomplete"]
    elapsed_s: float
    samples: int
    message: str


class StorageStatus(BaseModel):
    """Whether the server can save (settings, sets, runs); sent when that changes.

    ``writable`` false: "settings are not being saved" (``message`` says why)."""

    type: Literal["storage_status"] = "storage_status"
    writable: bool
    message: str


class ClientStats(BaseModel):
    type: Literal["client_stats"] = "client_stats"
    sent: int
    dropped: int


class MoveOutcome(BaseModel):
    """How a user's move to a target ended (``servotune.hub.movewatch``): the command's
    answer only said it was sent."""

    type: Literal["move_outcome"] = "move_outcome"
    axis: str
    command: str
    target: float
    outcome: Literal["arrived", "short", "limit", "fault", "stopped", "timeout"]
    position: float | None
    message: str


ServerMessage = Annotated[
    Hello
    | Telemetry
    | LinkStatus
    | AxisStatus
    | Params
    | Event
    | RunUpdate
    | StorageStatus
    | ClientStats
    | MoveOutcome,
    Field(discriminator="type"),
]


class Ping(BaseModel):
    type: Literal["ping"] = "ping"


ClientMessage = Annotated[Ping, Field(discriminator="type")]
