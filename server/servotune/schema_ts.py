"""Generate ``web/src/schema.gen.ts`` from the wire schema, the descriptor models and
the REST bodies.

``python -m servotune.schema_ts > web/src/schema.gen.ts`` writes it;
``python -m servotune.schema_ts --check web/src/schema.gen.ts`` fails (exit 1) when the
checked-in file is stale, which CI runs. Only the shapes used on the wire are
supported: str, int, float, bool, None, list, dict[str, X], Literal, unions and
nested models.
"""

from __future__ import annotations

import sys
import types
import typing
from pathlib import Path

from pydantic import BaseModel

from servotune import descriptor, schema

MODELS: list[type[BaseModel]] = [
    descriptor.Conversion,
    descriptor.BitDescriptor,
    descriptor.ParameterDescriptor,
    descriptor.ChannelDescriptor,
    descriptor.FlagDescriptor,
    descriptor.PlotDescriptor,
    descriptor.Choice,
    descriptor.ArgumentDescriptor,
    descriptor.MoveTarget,
    descriptor.CommandDescriptor,
    descriptor.ConsoleRule,
    descriptor.ConsoleDescriptor,
    descriptor.StopEffect,
    descriptor.LoopSignals,
    descriptor.JogPress,
    descriptor.JogDescriptor,
    descriptor.ParameterConstraint,
    descriptor.TwinDescriptor,
    descriptor.DeviceDescriptor,
    schema.AxisInfo,
    schema.LinkInfo,
    schema.Hello,
    schema.Telemetry,
    schema.LinkStatus,
    schema.AxisStatus,
    schema.Params,
    schema.Event,
    schema.RunUpdate,
    schema.StorageStatus,
    schema.ClientStats,
    schema.MoveOutcome,
    schema.Ping,
    schema.AxisState,
    schema.CommandResult,
    schema.StopResult,
    schema.ConsoleRequest,
    schema.ConsoleReply,
    schema.ErrorBody,
    schema.BenchField,
    schema.LawTerm,
    schema.LawGainSet,
    schema.ControllerLaw,
    # control lock (one block, servotune.hub.control_lock)
    schema.Welcome,
    schema.ControlHolder,
    schema.ControlPending,
    schema.ControlStatus,
    schema.ControlPrompt,
    schema.ControlReply,
    schema.TakeControl,
    schema.RequestControl,
    schema.ReleaseControl,
    schema.AnswerControl,
    schema.ForceControl,
    schema.Heartbeat,
]
# REST bodies. A response model's fields are all sent (like the websocket messages'); a
# request model's field with a default is optional in TypeScript (the client may leave it
# out). A model that is both (a PUT that answers with what it stored) is a response.
REST_RESPONSES: list[type[BaseModel]] = [
    schema.BenchLimits,
    schema.BenchInfo,
    schema.SavedSet,
    schema.ParamSet,
    schema.ParamSetComparison,
    schema.MarginTarget,
    schema.VerifyProfile,
    schema.WhatIfPlant,
    schema.WhatIfModel,
    schema.WhatIfInfo,
    schema.SessionInfo,
    schema.TicketReply,
    schema.TokenInfo,
    schema.NewToken,
    schema.UserInfo,
    schema.UserChanged,
    schema.AuditEntry,
]
REST_REQUESTS: list[type[BaseModel]] = [
    schema.BenchTestRequest,
    schema.SaveSetRequest,
    schema.AutoTuneRequest,
]
# Response bodies the server builds as dicts (the route documents the model): a field with
# a default may be absent, so it is optional in TypeScript like a request's.
REST_SHAPES: list[type[BaseModel]] = [
    schema.RunIdentity,
    schema.RunTest,
    schema.RunPlan,
    schema.RunMetrics,
    schema.RunReason,
    schema.RunQuality,
    schema.RunReturn,
    schema.BenchRun,
    schema.BenchRunDetail,
    schema.MarginReport,
    schema.AutoTuneSide,
    schema.AutoTuneRecommendation,
    schema.AutoTuneDecision,
    schema.AutoTuneProposal,
    schema.AutoTuneResult,
    schema.AutoTuneStopped,
    schema.AutoTuneSession,
    schema.FrfBode,
    schema.FrfNyquist,
    schema.FrfMargins,
    schema.FrfTrust,
    schema.FrfModel,
    schema.FrfMeasured,
    schema.FrfData,
]
ALIASES = {
    "BenchKind": schema.BenchKind,
    "RunStatus": schema.RunStatus,
    "AutoTuneAction": schema.AutoTuneAction,
    "AutoTuneGoal": schema.AutoTuneGoal,
    "AutoTuneTestKind": schema.AutoTuneTestKind,
    "AutoTuneState": schema.AutoTuneState,
    "AutoTuneVerdict": schema.AutoTuneVerdict,
    "MarginPreset": schema.MarginPreset,
    "LinkState": schema.LinkState,
    "AxisHealth": schema.AxisHealth,
    "EventLevel": schema.EventLevel,
    "ControlHolderKind": schema.ControlHolderKind,
    "ControlAction": schema.ControlAction,
}


def _members(annotated: object) -> list[type[BaseModel]]:
    """The models of an ``Annotated[A | B | ..., Field(discriminator=...)]`` union."""
    union = typing.get_args(annotated)[0]
    return list(typing.get_args(union)) or [union]


# Derived from the schema itself, so a new message type cannot be forgotten here.
UNIONS: dict[str, list[type[BaseModel]]] = {
    "ServerMessage": _members(schema.ServerMessage),
    "ClientMessage": _members(schema.ClientMessage),
    "ControlServerMessage": _members(schema.ControlServerMessage),
    "ControlClientMessage": _members(schema.ControlClientMessage),
}


_RENDERED = {*MODELS, *REST_RESPONSES, *REST_REQUESTS, *REST_SHAPES}


def ts_type(annotation: object) -> str:
    """The TypeScript spelling of a Python annotation."""
    for alias, target in ALIASES.items():
        if annotation == target:
            return alias
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if annotation is typing.Any:
        return "unknown"
    if annotation is str:
        return "string"
    if annotation in (int, float):
        return "number"
    if annotation is bool:
        return "boolean"
    if annotation is None or annotation is type(None):
        return "null"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation.__name__
    if origin is typing.Literal:
        return " | ".join(f'"{a}"' if isinstance(a, str) else str(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        # int | float is one TypeScript number
        return " | ".join(dict.fromkeys(ts_type(a) for a in args))
    if origin is tuple:
        return f"[{', '.join(ts_type(a) for a in args)}]"
    if origin is list:
        inner = ts_type(args[0])
        return f"({inner})[]" if "|" in inner else f"{inner}[]"
    if origin is dict:
        return f"Record<string, {ts_type(args[1])}>"
    raise TypeError(f"no TypeScript mapping for {annotation!r}")


def render() -> str:
    lines = [
        "// Generated by `python -m servotune.schema_ts` from server/servotune/schema/ and",
        "// descriptor.py. Do not edit: change the Python models and regenerate.",
        "",
    ]
    for alias, target in ALIASES.items():
        lines.append(f"export type {alias} = {_literal_of(target)};")
    lines.append("")
    for model in [*MODELS, *REST_RESPONSES]:
        lines.extend(_interface(model, optional_defaults=False))
    for model in [*REST_REQUESTS, *REST_SHAPES]:
        lines.extend(_interface(model, optional_defaults=True))
    for union, members in UNIONS.items():
        lines.append(f"export type {union} = {' | '.join(m.__name__ for m in members)};")
    lines.append("")
    return "\n".join(lines)


def _interface(model: type[BaseModel], *, optional_defaults: bool) -> list[str]:
    """``model`` as a TypeScript interface; with ``optional_defaults`` a field that has a
    default is optional (``name?: T``), otherwise every field is required."""
    hints = typing.get_type_hints(model)
    # A subclass of a rendered model extends it and lists only the fields it adds.
    parent = next((b for b in model.__bases__ if b in _RENDERED), None)
    inherited = parent.model_fields if parent is not None else {}
    extends = f" extends {parent.__name__}" if parent is not None else ""
    lines = [f"export interface {model.__name__}{extends} {{"]
    for name, field in model.model_fields.items():
        if name in inherited:
            if inherited[name].annotation != field.annotation:
                raise TypeError(f"{model.__name__}.{name} changes its parent's type")
            continue
        mark = "?" if optional_defaults and not field.is_required() else ""
        lines.append(f"  {field.alias or name}{mark}: {ts_type(hints[name])};")
    lines.append("}")
    lines.append("")
    return lines


def _literal_of(target: object) -> str:
    return " | ".join(f'"{a}"' for a in typing.get_args(target))


def main(argv: list[str]) -> int:
    text = render()
    if len(argv) == 2 and argv[0] == "--check":
        current = Path(argv[1]).read_text() if Path(argv[1]).exists() else ""
        if current != text:
            print(f"{argv[1]} is stale: run python -m servotune.schema_ts > {argv[1]}")
            return 1
        return 0
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
