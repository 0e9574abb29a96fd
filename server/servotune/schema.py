"""The one schema of everything the server and the web client exchange as JSON.

Every websocket message has an explicit ``type`` field (not derived from a class
name), so the client can switch on it and the TypeScript types generated from this
module (``python -m servotune.schema_ts``, checked in CI) stay in step with the server.

Websocket ``/ws`` (server -> client):
  ``hello`` once on connect, then ``telemetry`` batches (about 30 per second per
  axis), ``link_status`` and ``axis_status`` when they change (and every second),
  ``params`` after every read or write of device parameters, ``event`` for things a
  user should see in the log (stops, refusals, resets), ``storage_status`` when saving
  fails or works again, ``client_stats`` every second.
Client -> server: ``ping`` (answered by ``client_stats``). Commands go over REST.

Times ``t`` are seconds on the server's monotonic clock since the server started.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from servotune.descriptor import Conversion

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


# --- REST bodies ---------------------------------------------------------------------


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


class BenchField(BaseModel):
    """A field of the bench's test form (``GET /api/axes/{id}/bench``: ``fields``): the
    unit its number is in, and what it reads as in other units."""

    parameter: str | None = Field(
        description="the device parameter the test sets to this value (its unit and "
        "conversions are the field's); null: the field is not a device parameter"
    )
    unit: str
    conversions: list[Conversion]


class LawTerm(BaseModel):
    """One term of a controller law: ``coefficient x product(gains) x signal[n - delay]``."""

    coefficient: float
    gains: list[str] = Field(
        description="gain names, each read as the law's gain set prefix + name"
    )
    signal: Literal["error", "error_sum", "position"] = Field(
        description="error: target - position (counts); error_sum: the running sum of the "
        "error including this tick; position: the measured position (counts)"
    )
    delay: int = Field(default=0, ge=0, description="ticks")


class LawGainSet(BaseModel):
    """Which device parameters a law's gains are while the target moves or holds."""

    when: Literal["moving", "holding", "always"]
    prefix: str = Field(description="prepended to a term's gain names (e.g. 'kabh_')")


class ControllerLaw(BaseModel):
    """A device's controller law as data, every tick (the what-if view evaluates it):
    ``u = round(sum(terms) / divisor)``, clamped to the output limit. A linear analysis
    uses the holding gain set (else the one for always)."""

    terms: list[LawTerm]
    divisor: float
    rounding: Literal["none", "trunc"] = Field(
        description="none: u is the exact quotient; trunc: rounded towards zero"
    )
    gain_sets: list[LawGainSet]


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


# --- control lock per axis (servotune.hub.control_lock; websocket /ws) -------------------------
#
# Client -> server: ``take_control``, ``request_control``, ``release_control``,
# ``answer_control`` (the holder allows or denies a request), ``force_control`` (admin),
# ``heartbeat`` (renews the holder's lease a few times a second: the dead-man).
# Server -> client: ``welcome`` once after ``hello`` (this connection's client id, sent
# back as the ``X-Servotune-Client`` header on REST calls), ``control_status`` per axis
# whenever its holder or pending request changes (and in the snapshot on connect),
# ``control_prompt`` to the holder when someone requests its axis, ``control_reply`` to
# the sender of a control message (or a holder who lost an axis) saying what happened.

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


# --- REST bodies (server/servotune/api) -------------------------------------------------------
#
# Request and response bodies of the REST routes the web client calls. The TypeScript of
# these is generated beside the websocket types. A request model's field with a default
# may be left out by the client; a response model's fields are all sent.

BenchKind = Literal["move", "position_step", "velocity_step", "pwm_step", "frequency_response"]


class BenchLimits(BaseModel):
    """What the user allows the bench to do on one axis (checked before every test)."""

    max_distance_counts: int = Field(default=20_000, ge=1, le=1 << 25)
    max_velocity: int = Field(default=20_000, ge=1, le=1 << 31)
    # le: tuning.plants.OUTPUT_FULL_SCALE (the schema imports no tuning; a unit test
    # holds the two equal).
    max_pwm: int = Field(default=80, ge=1, le=255)
    max_duration_s: float = Field(default=10.0, gt=0, le=60)
    min_position_counts: int | None = Field(
        default=None,
        ge=-(1 << 31),
        le=(1 << 31) - 1,
        description="travel window: no test starts outside it, targets a position outside "
        "it or travels out of it (counts, with max_position_counts; null: no window)",
    )
    max_position_counts: int | None = Field(default=None, ge=-(1 << 31), le=(1 << 31) - 1)

    @model_validator(mode="after")
    def _window(self) -> BenchLimits:
        low, high = self.min_position_counts, self.max_position_counts
        if low is not None and high is not None and low >= high:
            raise ValueError(f"min_position_counts {low} must be below max_position_counts {high}")
        return self

    def outside(self, position: float) -> str | None:
        """Why ``position`` is outside the travel window, or None."""
        if self.min_position_counts is not None and position < self.min_position_counts:
            return f"{position:.0f} is below your min_position_counts {self.min_position_counts}"
        if self.max_position_counts is not None and position > self.max_position_counts:
            return f"{position:.0f} is above your max_position_counts {self.max_position_counts}"
        return None


class BenchTestRequest(BaseModel):
    """``POST /api/axes/{id}/bench/runs``: what to run (units are the device's)."""

    kind: BenchKind = Field(
        description="move | position_step | velocity_step | pwm_step | frequency_response"
    )
    distance: int = 0
    velocity: int = 0
    pwm: int = 0
    duration_s: float = Field(default=2.0, gt=0)
    amplitude: int = Field(
        default=0,
        description="frequency_response: peak of the multisine around the held "
        "position, counts (1..max_distance_counts)",
    )
    low_hz: float = Field(default=1.0, description="frequency_response: lowest tone, Hz")
    high_hz: float = Field(default=40.0, description="frequency_response: highest tone, Hz")
    loop: Literal["closed", "open"] = Field(
        default="closed",
        description="frequency_response: closed (position targets, ma) or open (PWM "
        "through spwm, peak `pwm`; SLAP2 only, needs a travel window and confirmation)",
    )
    confirm_open_loop: bool = Field(
        default=False, description="frequency_response, loop open: the user confirmed"
    )
    note: str = Field(default="", max_length=200)


class BenchInfo(BaseModel):
    """``GET /api/axes/{id}/bench``: the tests, limits and form fields of one axis."""

    kinds: list[str]
    limits: BenchLimits
    definitions: dict[str, str] = Field(description="how each metric is computed")
    fields: dict[str, BenchField] = Field(
        default_factory=dict,
        description="the test form's fields (distance, velocity, pwm): unit, conversions "
        "and the device parameter a field sets",
    )
    whatif: bool = Field(
        default=False, description="the what-if view works here (the device has a law)"
    )
    frequency_response: Literal["measured", "model"] | None = Field(
        default=None,
        description="measured: a multisine injected around the held position; model: the "
        "identified plant under the device's law; null: no frequency_response test",
    )


# A parameter set's name is a path segment of its URL: no "/", no leading or trailing
# space, and at least one character that is neither a dot nor a space, so "." and ".."
# (which a browser folds away when it normalises the URL) and " " can never be saved.
# Letters, digits, "_", spaces inside and . , + ( ) # - are allowed ("#" is sent as %23).
SET_NAME_PATTERN = r"^(?:[\w.,+()#-][\w .,+()#-]*)?[\w,+()#-](?:[\w .,+()#-]*[\w.,+()#-])?$"
SET_NAME_MAX = 60


class SaveSetRequest(BaseModel):
    """``POST .../param-sets``: the set's name (see ``SET_NAME_PATTERN``) and a note."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=SET_NAME_MAX, pattern=SET_NAME_PATTERN)
    note: str = Field(default="", max_length=200)


class SavedSet(BaseModel):
    """``POST .../param-sets``: the name saved and the values read from the device."""

    name: str
    params: dict[str, int]


class ParamSet(BaseModel):
    """A named set of parameter values as read from the device when it was saved."""

    name: str
    created_s: float = Field(description="unix seconds")
    device: str
    params: dict[str, int]
    note: str


class ParamSetComparison(BaseModel):
    """``device`` (read now) against the set; ``differing`` names the parameters whose
    values differ (the UI adds its own unsaved values as the third column)."""

    name: str
    device: dict[str, int]
    saved: dict[str, int]
    differing: list[str]


# --- what-if view (GET /api/axes/{id}/whatif) -------------------------------------------------
# Numbers the server computes may be sent as integers: ``int | float`` keeps each as sent.

Number = int | float
MarginPreset = Literal["stiff", "medium", "soft"]


class MarginTarget(BaseModel):
    """The phase and gain margins a set of gains is designed to (a preset)."""

    model_config = ConfigDict(extra="forbid")

    preset: MarginPreset
    phase_margin_deg: Number
    gain_margin_db: Number


class VerifyProfile(BaseModel):
    """The move of an auto-tune verification step, as the what-if view replays it."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["position_step", "move"]
    velocity_counts_s: Number
    acceleration_counts_s2: Number


class WhatIfPlant(BaseModel):
    """The identified velocity plant ``g / (s (tau s + 1))`` and where it comes from."""

    model_config = ConfigDict(extra="forbid")

    gain_counts_s_per_unit: Number
    tau_s: Number
    source: str


class WhatIfModel(BaseModel):
    """The plant discretised at the controller period and the device's law as data.

    ``plant_num``/``plant_den``: ``y[n] = sum(num[i] u[n-i]) - sum(den[i] y[n-i], i>=1)``
    with ``den[0] == 1``."""

    model_config = ConfigDict(extra="forbid")

    device: str
    law: str
    controller: ControllerLaw
    period_s: Number
    plant_num: list[float]
    plant_den: list[float]
    pwm_limit: Number
    plant: WhatIfPlant


class WhatIfInfo(BaseModel):
    """``GET /api/axes/{id}/whatif``: the gains now and their ranges, the margin targets,
    the verification move and the model (null with ``problem`` until identified)."""

    model_config = ConfigDict(extra="forbid")

    axis_id: str
    device: str
    gains: dict[str, Number | None]
    ranges: dict[str, tuple[Number, Number]]
    model: WhatIfModel | None
    problem: str | None
    target: MarginTarget = Field(description="what the margins are read against")
    targets: dict[str, MarginTarget]
    proposal: dict[str, Number] | None = Field(
        description="the auto-tune's proposed gains, if there is a proposal"
    )
    verify: VerifyProfile


# --- accounts (server/servotune/api/auth_routes.py) -------------------------------------------


class SessionInfo(BaseModel):
    """``GET /api/auth/session`` and ``POST /api/auth/login``: who the caller is (``user``
    null: nobody), how, and the CSRF token every state-changing call sends."""

    mode: Literal["local", "exposed"]
    user: str | None
    role: str | None
    permissions: list[str]
    csrf_token: str
    via: str | None = Field(
        default=None, description="session, token or local; null when nobody is logged in"
    )
    roles: list[str] = Field(description="every role, least privileged first")


class TicketReply(BaseModel):
    """``POST /api/auth/ws-ticket``: a single-use websocket ticket."""

    ticket: str
    expires_in_s: float


class TokenInfo(BaseModel):
    """An API token as listed (``GET /api/auth/tokens``): never its secret."""

    id: str
    user: str
    name: str
    role: str
    created_s: float = Field(description="unix seconds")
    expires_s: float = Field(description="unix seconds")
    last_used_s: float | None = Field(description="unix seconds; null: never used")


class NewToken(TokenInfo):
    """``POST /api/auth/tokens``: the new token with its secret, shown this once."""

    token: str


class UserInfo(BaseModel):
    """An account (``GET /api/users``, ``POST /api/users``)."""

    name: str
    role: str
    created_s: float = Field(description="unix seconds")


class UserChanged(BaseModel):
    """``PATCH /api/users/{name}``: the account's role after the change."""

    name: str
    role: str


class AuditEntry(BaseModel):
    """One entry of the audit log (``GET /api/audit``), newest first."""

    id: int
    t_s: float = Field(description="unix seconds")
    who: str
    action: str
    axis: str | None
    address: str | None
    before: str | None = Field(description="JSON of the state before, if recorded")
    after: str | None = Field(description="JSON of the state after, if recorded")
    result: str
    detail: str


# --- bench runs (GET /api/axes/{id}/bench/runs, GET /api/bench/runs/{id}) ---------------------
#
# These bodies are built by the bench from the stored run, not serialised through a model:
# the models below state their shape (the routes document them, tests check real runs
# against them). A field with a default may be absent from a body; every other one is there.

RunStatus = Literal["recording", "complete", "incomplete"]


class _Shape(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RunIdentity(_Shape):
    """Where the run was recorded: the link, its device path, the axis' address and name."""

    link: str
    path: str
    address: int
    name: str


class RunTest(_Shape):
    """The test as recorded (units are the device's); the frequency-response fields only
    on a ``frequency_response`` run."""

    kind: BenchKind
    distance: int
    velocity: int
    pwm: int
    duration_s: float
    note: str
    amplitude: int | None = None
    low_hz: float | None = None
    high_hz: float | None = None
    model_based: bool | None = Field(
        default=None, description="computed from the identified plant, nothing was sent"
    )
    loop: Literal["closed", "open"] | None = None


class RunPlan(_Shape):
    """What the metrics are computed on: the response column, its start and final
    values, the settling band (null: 2 % of the step) and the parameters the test set."""

    response: str
    y0: float
    y_final: float
    band: float | None
    overrides: dict[str, int]


FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
"""A JSON number (not a string), never NaN or infinite (JSON has neither)."""


class RunMetrics(_Shape):
    """The step-response metrics of a run, the one definition: ``bench.metrics.
    compute_metrics`` returns it, the bench stores and lists it, the auto-tune predicts
    it, an imported run's are checked against it. Times in s after the trigger t0; null
    where not defined, not reached or not trusted (``RunQuality.untrusted`` says why).
    What each one is: ``bench.metrics.DEFINITIONS`` (served as ``BenchInfo.definitions``).

    Strict (a number is a JSON number, not a string) and finite (NaN and infinities are
    refused: JSON has none), immutable once computed."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    step: FiniteFloat
    band: FiniteFloat | None
    samples: int = Field(ge=0)
    max_sample_gap_s: FiniteFloat | None
    rise_time_s: FiniteFloat | None
    overshoot_pct: FiniteFloat | None
    peak_time_s: FiniteFloat | None
    peak_value: FiniteFloat | None
    settling_time_s: FiniteFloat | None
    steady_state_error: FiniteFloat | None
    oscillations: int | None
    peak_following_error: FiniteFloat | None
    rms_following_error: FiniteFloat | None
    time_to_flag_s: dict[str, FiniteFloat | None]
    time_in_flag_s: dict[str, FiniteFloat]
    time_to_flag_resolution_s: dict[str, FiniteFloat | None] = Field(
        default_factory=dict,
        description="the ± of the flag times (flags are polled); absent on older runs",
    )
    time_in_flag_resolution_s: dict[str, FiniteFloat] = Field(default_factory=dict)


class RunReason(_Shape):
    code: str
    message: str


class RunQuality(_Shape):
    """How far the run's metrics can be trusted (``servotune.bench.quality``): ``bad`` runs
    are not comparable; ``untrusted`` names the metrics set to null and why."""

    status: Literal["good", "doubtful", "bad"]
    reasons: list[RunReason]
    untrusted: dict[str, str] = Field(default_factory=dict)
    sampling_rule: int | None = Field(
        default=None, description="the version of the sampling rule that judged the run"
    )


class RunReturn(_Shape):
    """The move back to where the test started, after the record."""

    ok: bool
    to: float
    error: float | None
    message: str


class BenchRun(_Shape):
    """A stored run without its samples (``GET /api/axes/{id}/bench/runs``; ``POST`` there
    answers the new run, without ``baseline``). ``columns[0]`` is ``t_s``."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    id: str
    axis_id: str
    created_s: float | None = Field(description="unix seconds")
    status: RunStatus
    baseline: bool = False
    axis_key: str
    device: str
    model: str
    identity: RunIdentity | None = None
    test: RunTest
    params: dict[str, int]
    plan: RunPlan
    columns: list[str]
    flags: list[str]
    metrics: RunMetrics | None
    quality: RunQuality | None = None
    message: str
    t0_s: float | None = Field(default=None, description="the trigger, server clock")
    imported_from: str | None = None
    autotune: dict[str, Any] | None = Field(
        default=None, description="what the auto-tune recorded with its runs"
    )
    excitation: dict[str, Any] | None = Field(
        default=None, description="frequency_response: the multisine and the targets sent"
    )
    plant_model: dict[str, Any] | None = Field(
        default=None, description="model-based frequency_response: the identified plant"
    )
    trigger_latency_s: float | None = None
    left_oscillating: dict[str, Any] | None = Field(
        default=None, description="the run left the axis oscillating: what was done"
    )
    loop_unverified: dict[str, Any] | None = Field(
        default=None,
        description="the check after the run could not tell whether the loop is at rest "
        "(telemetry too sparse): what was done",
    )
    return_: RunReturn | None = Field(default=None, alias="return")


class BenchRunDetail(BenchRun):
    """``GET /api/bench/runs/{id}``: the run with its sample rows, each ``[t_s, one value
    per columns[1..], [a 0/1 per flag, in flags order]]``."""

    samples: list[list[float | list[int] | None]]


# --- auto-tune (server/servotune/api/autotune_routes.py) --------------------------------------
#
# The request is validated by its model; the answers are built as dicts by the generic
# auto-tune (``autotune.service``, ``autotune.recommend``) around a device tuner's proposal
# and verification, and documented by the shapes below. They are device-neutral: gains
# are ``{parameter: value}`` under the descriptor's names, the identified model, the
# test tuned for and the rule's design notes are ``{name: value}`` maps the page lists
# as they come, so a new device's tuner needs no new type and the page no device branch.

AutoTuneAction = Literal["keep", "write"]
AutoTuneGoal = Literal["no_overshoot", "fast"]
"""no_overshoot: at most 1 % overshoot; fast: at most 10 % (each rule's limit)."""
AutoTuneTestKind = Literal["position_step", "move"]
AutoTuneState = Literal[
    "idle", "identifying", "proposed", "kept", "verifying", "verified", "failed"
]
AutoTuneVerdict = Literal["better", "not better", "unknown"]


class AutoTuneRequest(BaseModel):
    """``POST /api/axes/{id}/autotune/identify``: the user's limits and the goal."""

    # le: tuning.plants.OUTPUT_FULL_SCALE (the schema imports no tuning; a unit test
    # checks the two agree)
    max_pwm: int = Field(ge=1, le=255, description="largest open-loop PWM (-255..255)")
    max_distance_counts: int = Field(
        ge=1,
        le=1 << 24,
        description="no test travels further than this from where it starts (counts)",
    )
    response: AutoTuneGoal = Field(
        default="no_overshoot", description="no_overshoot (<= 1 %) or fast (<= 10 %)"
    )
    test: AutoTuneTestKind = Field(
        default="position_step",
        description="the test the gains are tuned for: position_step (sv/sa at maximum) "
        "or move (the axis' own sv/sa)",
    )
    direction: Literal[1, -1] = Field(
        default=1, description="1: identify and test towards positive counts, -1: negative"
    )
    # default: tuning.targets.DEFAULT_PRESET (checked by the same unit test)
    margins: MarginPreset = Field(
        default="medium",
        description="the margin target the gains are designed to: stiff (PM 40 deg / GM 6 dB), "
        "medium (45 deg / 8 dB) or soft (60 deg / 12 dB)",
    )
    distance: int | None = Field(
        default=None,
        ge=1,
        le=1 << 24,
        description="distance of the baseline and verification tests, counts "
        "(default: the device's, e.g. 1000 for a SLAP2, or half of max_distance_counts "
        "if smaller)",
    )


class MarginReport(_Shape):
    """A set of gains' margins on the identified model against a target: null margins
    where there is no crossover; ``warning`` says what misses the target."""

    gain_margin_db: Number | None
    phase_margin_deg: Number | None
    gain_crossover_hz: Number | None
    phase_crossover_hz: Number | None
    stable: bool | None
    target: MarginTarget
    meets_target: bool | None = Field(description="null: a margin could not be measured")
    warning: str | None


class AutoTuneSide(_Shape):
    """One side of the recommendation's comparison: margins on the model, predicted step."""

    phase_margin_deg: Number | None
    gain_margin_db: Number | None
    stable: bool | None
    meets_target: bool | None
    settling_time_s: Number | None
    overshoot_pct: Number | None


class AutoTuneRecommendation(_Shape):
    """Keep the gains in use or write the proposal, and why (``autotune.recommend``)."""

    action: AutoTuneAction
    reason: str
    target: MarginTarget
    proposal: AutoTuneSide
    current: AutoTuneSide


class AutoTuneDecision(_Shape):
    """What the user chose for a proposal (``POST .../autotune/keep`` answers it; the
    session's ``decision`` and ``history`` keep it)."""

    action: AutoTuneAction
    gains: dict[str, int]
    recommended: AutoTuneAction | None
    followed: bool
    reason: str | None
    at_s: Number = Field(description="unix seconds")
    identification_run_id: str | None


class AutoTuneProposal(_Shape):
    """``POST .../autotune/identify`` (and the session's ``proposal``): the identified
    model, the proposed gains against the ones in use, both predicted on the model."""

    model: dict[str, Number] = Field(description="the identified plant's parameters by name")
    test: dict[str, Number] = Field(
        description="the move tuned for: distance (counts, signed), band, velocity, ..."
    )
    response: AutoTuneGoal
    gains: dict[str, int] = Field(description="proposed, by the descriptor's parameter names")
    current_gains: dict[str, int] = Field(description="in use when identified")
    predicted: RunMetrics = Field(description="the proposal's step on the model")
    predicted_default: RunMetrics = Field(description="the gains in use, on the same model")
    predicted_peak_pwm: int
    predicted_excursion: int = Field(description="counts the proposal's test travels")
    default_excursion: int = Field(description="counts the gains in use would travel")
    design: dict[str, Any] = Field(description="the rule's notes, by name (shown as they come)")
    rule: str
    candidates: int
    simulations: int
    margins: MarginReport
    margins_default: MarginReport
    identification_run_id: str
    identification_run_ids: list[str] = Field(
        description="every attempt (a doubtful fit is repeated)"
    )
    travel_counts: Number
    warnings: list[str] = Field(description="doubts about the model, in words")
    baseline_possible: bool = Field(
        description="the gains in use stay within max_distance_counts: a baseline test runs"
    )
    recommendation: AutoTuneRecommendation
    device: str | None = Field(default=None, description="the tuner's device, where it says")
    model_samples: int | None = Field(
        default=None, description="samples the model was fitted to, where the tuner says"
    )


class AutoTuneResult(_Shape):
    """``POST .../autotune/accept`` after the verification: the baseline test with the
    previous gains, then the test with the proposal; predicted against measured."""

    gains: dict[str, int]
    previous_gains: dict[str, int]
    predicted: RunMetrics
    measured: RunMetrics | dict[str, None] = Field(
        description="the verification run's metrics; {} when the run has none (too few samples)"
    )
    predicted_default: RunMetrics
    baseline_measured: RunMetrics | None = Field(description="null: no baseline, or no metrics")
    verification_run_id: str
    baseline_run_id: str | None = Field(description="null: the baseline was skipped")
    baseline_note: str = Field(description="why the baseline was skipped; empty when it ran")
    verdict: AutoTuneVerdict
    verdict_reason: str | None = Field(description="why the verdict is what it is")


class AutoTuneStopped(_Shape):
    """``POST .../autotune/accept`` when the verification ended early (a 200 for a
    user's STOP; the session's ``result`` for any failure): the axis is stopped and the
    previous gains are written back (``unverified``: that failed, press Revert)."""

    stopped: bool
    unverified: bool
    message: str
    verdict: Literal["stopped", "failed"]
    previous_gains: dict[str, int]
    gains_in_force: dict[str, int | None]


class AutoTuneSession(_Shape):
    """``GET /api/axes/{id}/autotune``: the axis' auto-tune state, its last request,
    proposal, result and the user's decisions (``history``: newest last)."""

    axis: str
    state: AutoTuneState
    message: str
    request: AutoTuneRequest | None
    identification_run_id: str | None
    model: dict[str, Number] | None
    proposal: AutoTuneProposal | None
    result: AutoTuneResult | AutoTuneStopped | None
    decision: AutoTuneDecision | None
    history: list[AutoTuneDecision]
    updated_s: Number = Field(description="unix seconds; 0 before the first request")


# --- frequency response (GET /api/bench/runs/{id}/frf) ----------------------------------------
#
# Built in the compute worker by ``servotune.bench.frf.analyse_run`` (measured: from the
# run's samples; model: the identified plant under the device's law); documented shapes.
# Every non-finite number is sent as null.


class FrfBode(_Shape):
    """A Bode curve: magnitude (dB) and phase (deg) over frequency; the per-tone lists
    only on measured curves."""

    frequency_hz: list[float | None]
    magnitude_db: list[float | None]
    phase_deg: list[float | None]
    coherence: list[float | None] = Field(
        default_factory=list, description="magnitude-squared coherence over the periods"
    )
    relative_error: list[float | None] = Field(default_factory=list)
    error_db: list[float | None] = Field(
        default_factory=list, description="error bounds (about 95 %)"
    )
    error_deg: list[float | None] = Field(default_factory=list)
    trusted: list[bool] = Field(
        default_factory=list, description="known within the instrument's limits"
    )
    not_trusted_because: list[str | None] = Field(default_factory=list)
    measurable: list[bool] = Field(
        default_factory=list, description="open loop: L is known at the tone"
    )


class FrfNyquist(_Shape):
    """The open loop in the complex plane."""

    frequency_hz: list[float | None]
    re: list[float | None]
    im: list[float | None]
    measurable: list[bool] = Field(default_factory=list)


class FrfMargins(MarginReport):
    """Margins of the open loop against the target; a measured run says why a margin is
    null (``*_problem``) and how uncertain it is (``*_error_*``, about 95 %)."""

    gain_margin_problem: str | None = None
    phase_margin_problem: str | None = None
    gain_margin_error_db: Number | None = None
    phase_margin_error_deg: Number | None = None


class FrfTrust(_Shape):
    """Why a measured run's tones are (not) trusted (``servotune.tuning.frftrust``)."""

    trusted_tones: int
    tones: int
    max_error_db: Number
    max_error_deg: Number
    coverage: Number
    not_trusted: list[str]
    input_check_counts: Number | None
    input_check_excess_counts: Number | None
    input_check_samples_over: int
    stalled_samples_left_out: int
    stalled_targets_bounded: int
    max_latch_span_ms: Number | None
    spans: str
    max_gap_ms: Number | None
    gaps_over_50_ms: int


class FrfModel(_Shape):
    """The identified plant under the device's exact law with the run's gains."""

    margins: MarginReport
    bandwidth_hz: Number | None
    resonance_db: Number | None
    closed_loop: FrfBode
    open_loop: FrfBode
    nyquist: FrfNyquist
    plant: WhatIfPlant
    law: str


class FrfMeasured(_Shape):
    """The response measured from the run's samples at its tones: closed loop (targets
    injected) or open loop (``plant`` measured, the loop closed with the run's gains)."""

    loop: Literal["closed", "open"]
    closed_loop: FrfBode
    open_loop: FrfBode
    plant: FrfBode | None = Field(default=None, description="open loop: the plant measured")
    nyquist: FrfNyquist
    margins: FrfMargins
    input: str = Field(description="pwm (open loop), or the input model of the targets")
    usable_from_hz: Number | None
    usable_until_hz: Number | None
    sample_rate_hz: Number | None
    nyquist_hz: Number | None
    periods: int
    samples: int
    input_check_counts: Number | None
    trust: FrfTrust
    estimator: str
    not_measured_hz: list[Number | None] = Field(
        description="requested tones the wire cannot resolve: not sent, not measured"
    )
    not_measured_reason: str | None
    wire: dict[str, Any] | None = Field(description="the wire plan of the tones")
    bandwidth_hz: Number | None
    resonance_db: Number | None


class FrfData(_Shape):
    """``GET /api/bench/runs/{id}/frf``: either part may be null with a ``*_problem``."""

    run_id: str | None
    device: str
    model_based: bool
    loop: str
    low_hz: Number
    high_hz: Number
    measured: FrfMeasured | None
    measured_problem: str | None
    model: FrfModel | None
    model_problem: str | None
