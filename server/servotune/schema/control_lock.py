"""The control lock's websocket messages, one lock per axis (``servotune.hub.control_lock``;
websocket ``/ws``).

Client -> server: ``take_control``, ``request_control``, ``release_control``,
``answer_control`` (the holder allows or denies a request), ``force_control`` (admin),
``heartbeat`` (renews the holder's lease a few times a second: the dead-man).
Server -> client: ``welcome`` once after ``hello`` (this connection's client id, sent
back as the ``X-Servotune-Client`` header on REST calls), ``control_status`` per axis
whenever its holder or pending request changes (and in the snapshot on connect),
``control_prompt`` to the holder when someone requests its axis, ``control_reply`` to
the sender of a control message (or a holder who lost an axis) saying what happened.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, Field

ControlHolderKind = Literal["user", "autopilot", "server"]
ControlAction = Literal["take", "request", "release", "answer", "force", "lapse", "grant", "deny"]


class Welcome(BaseModel):
    """This connection's identity. ``client_id`` is secret to this tab (it authorises REST
    changes of the axes it holds); ``client_tag`` is its public name in ``control_status``."""

    type: Literal["welcome"] = "welcome"
    client_id: str
    client_tag: str
    user: str
    permissions: list[str]
    heartbeat_period_s: float = Field(description="send a heartbeat at least this often")
    lease_s: float = Field(description="the server stops your axes this long after the last one")


class ControlHolder(BaseModel):
    kind: ControlHolderKind
    user: str = Field(description="user name, 'autopilot', or 'server' (start-up stop)")
    client_tag: str | None = Field(description="public tag of the holding connection")
    since_s: float = Field(description="server time the hold began")


class ControlPending(BaseModel):
    user: str
    client_tag: str
    expires_s: float = Field(description="server time the request is decided without answer")


class ControlStatus(BaseModel):
    type: Literal["control_status"] = "control_status"
    axis: str
    holder: ControlHolder | None = Field(description="null: nobody holds the axis")
    pending: ControlPending | None


class ControlPrompt(BaseModel):
    """To the holder: someone asks for an axis; answer with ``answer_control``."""

    type: Literal["control_prompt"] = "control_prompt"
    axis: str
    requester: str
    requester_tag: str
    timeout_s: float
    idle_grant_s: float = Field(description="no answer: granted if you were idle this long")


class ControlReply(BaseModel):
    """What came of a control message (or why this connection lost an axis)."""

    type: Literal["control_reply"] = "control_reply"
    axis: str | None
    action: ControlAction
    ok: bool
    message: str


ControlServerMessage = Annotated[
    Welcome | ControlStatus | ControlPrompt | ControlReply, Field(discriminator="type")
]


class TakeControl(BaseModel):
    type: Literal["take_control"] = "take_control"
    axis: str = Field(max_length=200)


class RequestControl(BaseModel):
    type: Literal["request_control"] = "request_control"
    axis: str = Field(max_length=200)


class ReleaseControl(BaseModel):
    type: Literal["release_control"] = "release_control"
    axis: str = Field(max_length=200)


class AnswerControl(BaseModel):
    type: Literal["answer_control"] = "answer_control"
    axis: str = Field(max_length=200)
    allow: bool


class ForceControl(BaseModel):
    type: Literal["force_control"] = "force_control"
    axis: str = Field(max_length=200)


class Heartbeat(BaseModel):
    """Renews the tab's lease. Sent by the tab's heartbeat worker on a socket of its own
    (``/ws?beat=<client_id>``), so a page busy drawing does not delay it. While a
    hold-to-run control (a jog) is engaged, ``page_age_ms`` is how long ago the page's
    own thread last ran (a page frozen with a jog held loses its axes after
    ``ControlSettings.frozen_page_s``: it could not release the jog); null otherwise."""

    type: Literal["heartbeat"] = "heartbeat"
    page_age_ms: int | None = Field(default=None, ge=0, le=86_400_000)


ControlClientMessage = Annotated[
    TakeControl | RequestControl | ReleaseControl | AnswerControl | ForceControl | Heartbeat,
    Field(discriminator="type"),
]
