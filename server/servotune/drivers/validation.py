"""Checks of user input against a device descriptor, shared by the hub and drivers.

Every check raises ``InvalidArgumentError`` naming the field and the allowed range
before anything is sent to a device.
"""

from __future__ import annotations

from collections.abc import Mapping

from servotune.descriptor import DeviceDescriptor
from servotune.drivers.base import InvalidArgumentError


def _integer_in(name: str, value: object, minimum: int, maximum: int, allowed: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidArgumentError(name, f"{name} must be an integer in {allowed}")
    if not minimum <= value <= maximum:
        raise InvalidArgumentError(name, f"{name} = {value} is out of range: allowed {allowed}")
    return value


def validate_params(descriptor: DeviceDescriptor, values: Mapping[str, object]) -> dict[str, int]:
    """Every value must be a known parameter and an integer within its range."""
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
    return checked


def validate_command(
    descriptor: DeviceDescriptor, name: str, args: Mapping[str, object]
) -> dict[str, int]:
    """The command must exist; its arguments must all be given, known and in range."""
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
            raise InvalidArgumentError(argument.name, f"{name} needs {argument.name} ({allowed})")
        checked[argument.name] = _integer_in(
            argument.name, args[argument.name], argument.minimum, argument.maximum, allowed
        )
    return checked
