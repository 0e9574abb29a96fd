"""Checks of user input against a device descriptor, shared by the hub and drivers.

Every check raises ``InvalidArgumentError`` naming the field and the allowed range
before anything is sent to a device.
"""

from __future__ import annotations

from collections.abc import Mapping

from servotune.descriptor import DeviceDescriptor
from servotune.link.base import InvalidArgumentError


def _integer_in(name: str, value: object, minimum: int, maximum: int, allowed: str) -> int:
    # JSON does not tell 381 from 381.0 and JSON Schema's "integer" includes both: an
    # integral float is that integer. 381.5, NaN and infinities are not.
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidArgumentError(name, f"{name} must be an integer in {allowed}")
    if not minimum <= value <= maximum:
        raise InvalidArgumentError(name, f"{name} = {value} is out of range: allowed {allowed}")
    return value


def validate_params(
    descriptor: DeviceDescriptor,
    values: Mapping[str, object],
    current: Mapping[str, int] | None = None,
) -> dict[str, int]:
    """Every value must be a known parameter and an integer within its range, and the
    descriptor's ``constraints`` must hold for the values merged over ``current`` (the
    device's values as last read or written; a constraint whose other side is not
    known yet is checked when it is)."""
    if not values:
        raise InvalidArgumentError("body", "no parameters given")
    checked: dict[str, int] = {}
    for name, value in values.items():
        try:
            parameter = descriptor.parameter(name)
        except KeyError:
            known = ", ".join(p.name for p in descriptor.parameters)
            raise InvalidArgumentError(
                name, f"{name}: unknown parameter for {descriptor.model} (known: {known})"
            ) from None
        unit = f" {parameter.unit}" if parameter.unit else ""
        allowed = f"{parameter.minimum}..{parameter.maximum}{unit}"
        checked[name] = _integer_in(name, value, parameter.minimum, parameter.maximum, allowed)
        if parameter.choices and checked[name] not in {c.value for c in parameter.choices}:
            listed = ", ".join(f"{c.value} ({c.label})" for c in parameter.choices)
            raise InvalidArgumentError(name, f"{name} = {checked[name]} is not one of {listed}")
    validate_constraints(descriptor, checked, current or {})
    return checked


def validate_constraints(
    descriptor: DeviceDescriptor, written: Mapping[str, int], current: Mapping[str, int]
) -> None:
    """Raise for the first constraint ``lower <= upper`` that the written values break
    (merged over ``current``); the error names a parameter being written."""
    merged = {**current, **written}
    for constraint in descriptor.constraints:
        lower, upper = constraint.lower, constraint.upper
        if lower not in written and upper not in written:
            continue  # nothing written changes this pair: not this request's fault
        if lower not in merged or upper not in merged:
            continue
        if merged[lower] <= merged[upper]:
            continue
        field = lower if lower in written else upper
        raise InvalidArgumentError(
            field,
            f"{field}: {lower} ({merged[lower]}) must not exceed {upper} ({merged[upper]}): "
            f"{constraint.message}",
        )


def validate_command(
    descriptor: DeviceDescriptor, name: str, args: Mapping[str, object]
) -> dict[str, int]:
    """The command must exist; its arguments must be known and in range. A required
    argument must be given; an optional one that is omitted takes the descriptor's
    ``default`` (the returned mapping always holds every argument)."""
    try:
        command = descriptor.command(name)
    except KeyError:
        known = ", ".join(c.name for c in descriptor.commands)
        raise InvalidArgumentError(
            "command", f"unknown command {name!r} (known: {known})"
        ) from None
    extra = sorted(set(args) - {a.name for a in command.arguments})
    if extra:
        raise InvalidArgumentError(extra[0], f"{name} takes no argument {extra[0]!r}")
    checked: dict[str, int] = {}
    for argument in command.arguments:
        allowed = f"{argument.minimum}..{argument.maximum}"
        if argument.unit:
            allowed += f" {argument.unit}"
        if argument.name not in args:
            if argument.required:
                raise InvalidArgumentError(
                    argument.name, f"{name} needs {argument.name} ({allowed})"
                )
            checked[argument.name] = argument.default
            continue
        checked[argument.name] = _integer_in(
            argument.name, args[argument.name], argument.minimum, argument.maximum, allowed
        )
    return checked
