"""REST bodies of one axis: its state, a command, the console, STOP, and the error body
every 4xx/5xx answers with."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from servotune.schema.websocket import AxisHealth, LinkState


class AxisState(BaseModel):
    """``GET /api/axes/{id}/state``: the latest telemetry sample."""

    t: float
    position: float
    following_error: float
    velocity: float
    channels: dict[str, float]
    flags: dict[str, bool]
    health: AxisHealth
    link_state: LinkState


class CommandRequest(BaseModel, extra="allow"):
    """``POST /api/axes/{id}/commands``: ``{"command": name, <argument>: value, ...}``.

    The arguments are the command's ``arguments`` in the axis' descriptor (integers in
    their ranges; a ``required`` one must be given, others default). The live OpenAPI
    replaces this schema by one variant per device and command (``servotune.api.openapi``).
    Unknown arguments answer 422 naming them.
    """

    command: str = Field(min_length=1, max_length=64)


class CommandResult(BaseModel):
    command: str
    sent: list[str] = Field(description="wire lines sent, in order")
    message: str
    outcome_pending: bool = Field(
        default=False,
        description="a move to a target: the device took it; a move_outcome message says "
        "how it ended (arrived, or where a limit switch or a STOP stopped it)",
    )


# A console line is printable: a control character (CR, LF, Ctrl-X, Ctrl-K, ...) inside a
# line would reach the wire and split or abort the device's command (Ctrl-X discards the
# SLAP2's input; a CR ends the command early). The devices' control bytes have their own
# descriptor commands (e.g. SLAP2 ``abort_calibration`` sends Ctrl-K). At least one
# character that is not a space: the SLAP2 driver removes spaces.
CONSOLE_LINE_PATTERN = r"^[^\x00-\x1f\x7f]*[^\x00-\x20\x7f][^\x00-\x1f\x7f]*$"


class ConsoleRequest(BaseModel):
    """``POST /api/axes/{id}/console``: one printable line, no control characters."""

    model_config = ConfigDict(extra="forbid")

    line: str = Field(min_length=1, max_length=64, pattern=CONSOLE_LINE_PATTERN)


class StopResult(BaseModel):
    """``POST /api/stop``: the axes whose stop could not be sent (each also gets an
    ``event`` saying why and what happens next)."""

    failed: list[str]


class ConsoleReply(BaseModel):
    line: str
    sent: str
    reply: list[str]
    error: str | None


class ErrorBody(BaseModel):
    """Every 4xx/5xx body: ``detail`` says what is wrong in words a user can act on."""

    detail: str
    field: str | None = None
    kind: Literal["measurement"] | None = Field(
        default=None,
        description="measurement: a measurement could not support its result (too few "
        "samples, ...); the device refused nothing",
    )
