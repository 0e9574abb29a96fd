"""The one schema of everything the server and the web client exchange as JSON.

Import every name from here (``from servotune.schema import RunMetrics``): each public
name of the package's modules is re-exported, and its TypeScript is generated from here
(``python -m servotune.schema_ts``, checked in CI), so server and client stay in step.
Every websocket message has an explicit ``type`` field. Of a REST body, a request
model's field with a default may be left out by the client; a response model's fields
are all sent; a documented shape (built as a dict) may leave out a field with a default.

The modules, by seam:
  ``websocket``     the ``/ws`` stream (hello, telemetry, status, params, events, ...)
  ``control_lock``  the control lock's websocket messages
  ``axes``          one axis over REST: state, command, console, STOP, the error body
  ``law``           a device's controller law as data
  ``bench``         the bench's test form, limits, test request and description
  ``param_sets``    named parameter sets
  ``whatif``        the what-if view and margins against a target
  ``accounts``      sessions, API tokens, users, the audit log
  ``runs``          stored bench runs and their metrics
  ``autotune``      the auto-tune's request, proposal, result and session
  ``frf``           the frequency response of a run
  ``base``          what they share: the documented shapes' base, JSON numbers
"""

from servotune.schema.accounts import (
    AuditEntry,
    NewToken,
    SessionInfo,
    TicketReply,
    TokenInfo,
    UserChanged,
    UserInfo,
)
from servotune.schema.autotune import (
    AutoTuneAction,
    AutoTuneDecision,
    AutoTuneGoal,
    AutoTuneProposal,
    AutoTuneRecommendation,
    AutoTuneRequest,
    AutoTuneResult,
    AutoTuneSession,
    AutoTuneSide,
    AutoTuneState,
    AutoTuneStopped,
    AutoTuneTestKind,
    AutoTuneVerdict,
)
from servotune.schema.axes import (
    CONSOLE_LINE_PATTERN,
    AxisState,
    CommandRequest,
    CommandResult,
    ConsoleReply,
    ConsoleRequest,
    ErrorBody,
    StopResult,
)
from servotune.schema.base import (
    FiniteFloat,
    Number,
)
from servotune.schema.bench import (
    BenchField,
    BenchInfo,
    BenchKind,
    BenchLimits,
    BenchTestRequest,
)
from servotune.schema.control_lock import (
    AnswerControl,
    ControlAction,
    ControlClientMessage,
    ControlHolder,
    ControlHolderKind,
    ControlPending,
    ControlPrompt,
    ControlReply,
    ControlServerMessage,
    ControlStatus,
    ForceControl,
    Heartbeat,
    ReleaseControl,
    RequestControl,
    TakeControl,
    Welcome,
)
from servotune.schema.frf import (
    FrfBode,
    FrfData,
    FrfMargins,
    FrfMeasured,
    FrfModel,
    FrfNyquist,
    FrfTrust,
)
from servotune.schema.law import (
    ControllerLaw,
    LawGainSet,
    LawTerm,
)
from servotune.schema.param_sets import (
    SET_NAME_MAX,
    SET_NAME_PATTERN,
    ParamSet,
    ParamSetComparison,
    SavedSet,
    SaveSetRequest,
)
from servotune.schema.runs import (
    BenchRun,
    BenchRunDetail,
    RunIdentity,
    RunMetrics,
    RunPlan,
    RunQuality,
    RunReason,
    RunReturn,
    RunStatus,
    RunTest,
)
from servotune.schema.websocket import (
    AxisHealth,
    AxisInfo,
    AxisStatus,
    ClientMessage,
    ClientStats,
    Event,
    EventLevel,
    Hello,
    LinkInfo,
    LinkState,
    LinkStatus,
    MoveOutcome,
    Params,
    Ping,
    RunUpdate,
    ServerMessage,
    StorageStatus,
    Telemetry,
)
from servotune.schema.whatif import (
    MarginPreset,
    MarginReport,
    MarginTarget,
    VerifyProfile,
    WhatIfInfo,
    WhatIfModel,
    WhatIfPlant,
)

__all__ = [
    "CONSOLE_LINE_PATTERN",
    "SET_NAME_MAX",
    "SET_NAME_PATTERN",
    "AnswerControl",
    "AuditEntry",
    "AutoTuneAction",
    "AutoTuneDecision",
    "AutoTuneGoal",
    "AutoTuneProposal",
    "AutoTuneRecommendation",
    "AutoTuneRequest",
    "AutoTuneResult",
    "AutoTuneSession",
    "AutoTuneSide",
    "AutoTuneState",
    "AutoTuneStopped",
    "AutoTuneTestKind",
    "AutoTuneVerdict",
    "AxisHealth",
    "AxisInfo",
    "AxisState",
    "AxisStatus",
    "BenchField",
    "BenchInfo",
    "BenchKind",
    "BenchLimits",
    "BenchRun",
    "BenchRunDetail",
    "BenchTestRequest",
    "ClientMessage",
    "ClientStats",
    "CommandRequest",
    "CommandResult",
    "ConsoleReply",
    "ConsoleRequest",
    "ControlAction",
    "ControlClientMessage",
    "ControlHolder",
    "ControlHolderKind",
    "ControlPending",
    "ControlPrompt",
    "ControlReply",
    "ControlServerMessage",
    "ControlStatus",
    "ControllerLaw",
    "ErrorBody",
    "Event",
    "EventLevel",
    "FiniteFloat",
    "ForceControl",
    "FrfBode",
    "FrfData",
    "FrfMargins",
    "FrfMeasured",
    "FrfModel",
    "FrfNyquist",
    "FrfTrust",
    "Heartbeat",
    "Hello",
    "LawGainSet",
    "LawTerm",
    "LinkInfo",
    "LinkState",
    "LinkStatus",
    "MarginPreset",
    "MarginReport",
    "MarginTarget",
    "MoveOutcome",
    "NewToken",
    "Number",
    "ParamSet",
    "ParamSetComparison",
    "Params",
    "Ping",
    "ReleaseControl",
    "RequestControl",
    "RunIdentity",
    "RunMetrics",
    "RunPlan",
    "RunQuality",
    "RunReason",
    "RunReturn",
    "RunStatus",
    "RunTest",
    "RunUpdate",
    "SaveSetRequest",
    "SavedSet",
    "ServerMessage",
    "SessionInfo",
    "StopResult",
    "StorageStatus",
    "TakeControl",
    "Telemetry",
    "TicketReply",
    "TokenInfo",
    "UserChanged",
    "UserInfo",
    "VerifyProfile",
    "Welcome",
    "WhatIfInfo",
    "WhatIfModel",
    "WhatIfPlant",
]
