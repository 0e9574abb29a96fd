"""The live OpenAPI: command and parameter bodies stated per device, from the descriptors.

FastAPI can only describe ``POST /api/axes/{id}/commands`` and ``PATCH .../params`` as
"an object": what they accept depends on the axis' device. Once the hub runs (the
descriptors are known), the schema is rebuilt so that it states the real constraints:

- the templated operations get a union (``anyOf``) of one variant per device and
  command (``command`` a constant, each argument an integer in its range, the required
  ones required, nothing else allowed) and, for params, every parameter name of every
  device as an integer in the widest range any device allows;
- every axis gets concrete operations ``/api/axes/<axis>/commands`` and
  ``/api/axes/<axis>/params`` with exactly its device's body (OpenAPI matches concrete
  paths before templated ones), so a client (or a fuzzer) generating a body for that
  path gets one the server accepts, except for refusals that depend on the device's
  state (409).

Cross-field constraints (descriptor ``constraints``) cannot be stated in JSON Schema
across the device's current values: they are listed in the params description.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from servotune.descriptor import CommandDescriptor, DeviceDescriptor, ParameterDescriptor

COMMANDS_PATH = "/api/axes/{axis_id}/commands"
PARAMS_PATH = "/api/axes/{axis_id}/params"


def command_schema(device: str, command: CommandDescriptor) -> dict[str, Any]:
    """The request body of one command of one device (JSON Schema)."""
    properties: dict[str, Any] = {"command": {"const": command.name, "type": "string"}}
    required = ["command"]
    for argument in command.arguments:
        prop: dict[str, Any] = {
            "type": "integer",
            "minimum": argument.minimum,
            "maximum": argument.maximum,
            "title": argument.label,
        }
        if argument.choices:
            prop["enum"] = [c.value for c in argument.choices]
        if argument.required:
            required.append(argument.name)
        else:
            prop["default"] = argument.default
        if argument.unit:
            prop["description"] = argument.unit
        properties[argument.name] = prop
    return {
        "type": "object",
        "title": f"{device} {command.name}",
        "description": command.description,
        "properties": properties,
        "required": required,
        "additionalProperties": False,
    }


def _parameter_schema(parameter: ParameterDescriptor) -> dict[str, Any]:
    unit = f" {parameter.unit}" if parameter.unit else ""
    schema: dict[str, Any] = {
        "type": "integer",
        "minimum": parameter.minimum,
        "maximum": parameter.maximum,
        "title": parameter.label,
        "description": f"{parameter.minimum}..{parameter.maximum}{unit}",
    }
    if parameter.choices:
        schema["enum"] = [c.value for c in parameter.choices]
    return schema


def params_schema(descriptors: Sequence[DeviceDescriptor]) -> dict[str, Any]:
    """The PATCH params body for axes of these devices (the widest range per name)."""
    properties: dict[str, dict[str, Any]] = {}
    for descriptor in descriptors:
        for parameter in descriptor.parameters:
            schema = _parameter_schema(parameter)
            known = properties.get(parameter.name)
            if known is None:
                properties[parameter.name] = schema
            elif known != schema:
                # An enumeration stays one only if both devices enumerate the name.
                both = "enum" in known and "enum" in schema
                values = set(known.pop("enum", [])) | set(schema.get("enum", []))
                if both:
                    known["enum"] = sorted(values)
                known["minimum"] = min(known["minimum"], parameter.minimum)
                known["maximum"] = max(known["maximum"], parameter.maximum)
                known["description"] = "range depends on the device (see its descriptor)"
    constraints = [
        f"{d.device}: {c.lower} <= {c.upper} ({c.message})"
        for d in descriptors
        for c in d.constraints
    ]
    description = "Parameters to write, by descriptor name; at least one."
    if constraints:
        description += (
            " Checked across fields against the device's current values: "
            + "; ".join(constraints)
            + "."
        )
    return {
        "type": "object",
        "properties": properties,
        "minProperties": 1,
        "additionalProperties": False,
        "description": description,
        "examples": [{"kp": 60, "kd": 120}],
    }


def commands_schema(descriptors: Sequence[DeviceDescriptor]) -> dict[str, Any]:
    """The command body for axes of these devices: one variant per device and command."""
    variants: list[dict[str, Any]] = []
    seen: set[str] = set()
    for descriptor in descriptors:
        for command in descriptor.commands:
            variant = command_schema(descriptor.device, command)
            key = json.dumps(variant, sort_keys=True)
            if key not in seen:
                seen.add(key)
                variants.append(variant)
    if len(variants) == 1:
        return variants[0]
    return {
        "anyOf": variants,
        "description": "A command of the axis' device with its arguments "
        "(GET .../descriptor lists them; a body for another device answers 422).",
    }


def _set_body(operation: dict[str, Any], schema: dict[str, Any]) -> None:
    body = operation.setdefault("requestBody", {"required": True, "content": {}})
    body["required"] = True
    body["content"] = {"application/json": {"schema": schema}}


def _concrete(
    operation: dict[str, Any], axis_id: str, schema: dict[str, Any] | None
) -> dict[str, Any]:
    concrete = copy.deepcopy(operation)
    concrete["parameters"] = [
        p for p in concrete.get("parameters", []) if p.get("name") != "axis_id"
    ]
    if not concrete["parameters"]:
        del concrete["parameters"]
    concrete["operationId"] = f"{operation.get('operationId', 'op')}_{axis_id}"
    concrete["summary"] = f"{operation.get('summary', '')} ({axis_id})".strip()
    if schema is not None:
        _set_body(concrete, schema)
    return concrete


def device_openapi(app: FastAPI, axes: Sequence[tuple[str, DeviceDescriptor]]) -> dict[str, Any]:
    """The app's OpenAPI with command and params bodies stated for these axes."""
    schema = get_openapi(
        title=app.title,
        version=app.version,
        summary=app.summary,
        description=app.description,
        routes=app.routes,
    )
    paths: dict[str, Any] = schema["paths"]
    descriptors = [d for _, d in axes]
    command_op = paths.get(COMMANDS_PATH, {}).get("post")
    params_op = paths.get(PARAMS_PATH, {}).get("patch")
    if descriptors and command_op is not None:
        _set_body(command_op, commands_schema(descriptors))
    if descriptors and params_op is not None:
        _set_body(params_op, params_schema(descriptors))
    for axis_id, descriptor in axes:
        if command_op is not None:
            path = COMMANDS_PATH.replace("{axis_id}", axis_id)
            paths[path] = {"post": _concrete(command_op, axis_id, commands_schema([descriptor]))}
        if params_op is not None:
            path = PARAMS_PATH.replace("{axis_id}", axis_id)
            get_op = paths[PARAMS_PATH].get("get")
            entry = {"patch": _concrete(params_op, axis_id, params_schema([descriptor]))}
            if get_op is not None:
                # The same path answers GET too: a concrete path item must list every
                # method, or a client would conclude GET is not allowed there.
                entry["get"] = _concrete(get_op, axis_id, None)
            paths[path] = entry
    return schema
