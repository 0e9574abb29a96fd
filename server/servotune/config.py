"""Server configuration: link specs from the command line or a TOML file.

A link spec reads ``device:path?key=value&...``, for example
``slap2:/dev/ttyUSB0?addresses=0,1&baud=19200&lines=512`` (``name=`` sets the link
id; ``names=Lift,Gripper`` names the axes in address order). The same links can be
written in a TOML file::

    host = "127.0.0.1"
    port = 8000

    [[link]]
    device = "slap2"
    path = "/dev/ttyUSB0"
    addresses = [0, 1]
    baud = 19200
    lines = 512
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol
from urllib.parse import parse_qsl

# The standard serial rates a link spec may ask for (a device may refuse some).
BAUD_RATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)


@dataclass(frozen=True, slots=True, kw_only=True)
class LinkRules:
    """How a link spec of one device reads (its ``DeviceEntry.link_rules``).

    ``addressing``: ``"modules"`` — ``addresses=`` lists modules on one line, each in
    ``address_range``; ``"fixed"`` — the device's axes are ``fixed_addresses`` whatever
    is asked (``addresses=`` is still checked against ``address_range``); ``"slave"`` —
    one axis, the device's position on an EtherCAT bus (``slave=``, in ``slave_range``,
    default its first).
    ``default_baud`` None: not a serial device (no ``baud=``; the spec's baud is 0).
    ``address_range``: the values ``addresses=`` (and the CLI's ``--addresses``) accept;
    a device fact, so each device states it.
    """

    default_baud: int | None
    address_range: tuple[int, int]
    addressing: Literal["modules", "fixed", "slave"] = "modules"
    fixed_addresses: tuple[int, ...] = ()
    slave_range: tuple[int, int] = (1, 65535)
    example: str = ""  # a link spec for error messages and help


class LinkRulesSource(Protocol):
    """What reading a link spec needs of the registry."""

    def names(self) -> Sequence[str]: ...

    def link_rules(self, device: str) -> LinkRules: ...


class ConfigError(ValueError):
    """A link spec or config file that cannot be used; the message names the field."""


@dataclass(slots=True)
class LinkSpec:
    device: str
    path: str
    link_id: str
    baud: int  # 0: not a serial link
    addresses: list[int] = field(default_factory=lambda: [0])
    lines: int = 512
    names: dict[int, str] = field(default_factory=dict)


def _link_id_from_path(device: str, path: str) -> str:
    stem = re.sub(r"[^A-Za-z0-9]+", "-", Path(path).name).strip("-") or "link"
    return f"{device}-{stem}"


def _int(field_name: str, text: Any, low: int, high: int) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise ConfigError(f"{field_name} must be an integer, got {text!r}") from None
    if not low <= value <= high:
        raise ConfigError(f"{field_name} must be in {low}..{high}, got {value}")
    return value


def link_from_mapping(data: dict[str, Any], devices: LinkRulesSource) -> LinkSpec:
    """Build and check a LinkSpec from a dict (TOML table or parsed link spec)."""
    device = str(data.get("device", ""))
    known = devices.names()
    if device not in known:
        raise ConfigError(f"device must be one of {', '.join(known)}, got {device!r}")
    rules = devices.link_rules(device)
    path = str(data.get("path", ""))
    if not path:
        raise ConfigError("path is missing (e.g. /dev/ttyUSB0)")
    if rules.default_baud is None:
        baud = 0  # not a serial link: no baud rate
    else:
        baud = _int("baud", data.get("baud", rules.default_baud), 300, 1_000_000)
        if baud not in BAUD_RATES:
            raise ConfigError(f"baud must be one of {', '.join(map(str, BAUD_RATES))}, got {baud}")
    raw_addresses = data.get("addresses", [0])
    if isinstance(raw_addresses, str):
        raw_addresses = [a for a in raw_addresses.split(",") if a.strip()]
    low, high = rules.address_range
    addresses = [_int("addresses", a, low, high) for a in raw_addresses]
    if rules.addressing == "fixed":
        addresses = list(rules.fixed_addresses)  # nothing to address: the axes are fixed
    elif rules.addressing == "slave":
        addresses = [_int("slave", data.get("slave", rules.slave_range[0]), *rules.slave_range)]
    if not addresses or len(set(addresses)) != len(addresses):
        raise ConfigError(f"addresses must list distinct module addresses {low}..{high}")
    lines = _int("lines", data.get("lines", 512), 1, 1_000_000)
    raw_names = data.get("names", [])
    if isinstance(raw_names, str):
        raw_names = raw_names.split(",")
    names = {a: str(n) for a, n in zip(addresses, raw_names, strict=False) if str(n).strip()}
    link_id = str(data.get("name") or _link_id_from_path(device, path))
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", link_id):
        raise ConfigError(f"name may use letters, digits, '-', '_' and '.', got {link_id!r}")
    return LinkSpec(device, path, link_id, baud, addresses, lines, names)


def parse_link_spec(spec: str, devices: LinkRulesSource) -> LinkSpec:
    """Parse ``device:path?key=value&...`` for one of ``devices``."""
    device, sep, rest = spec.partition(":")
    if not sep:
        example = devices.link_rules(devices.names()[0]).example
        raise ConfigError(f"link spec must look like {example!r}, got {spec!r}")
    path, _, query = rest.partition("?")
    data: dict[str, Any] = {"device": device, "path": path}
    for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=False):
        if key not in ("addresses", "baud", "lines", "name", "names", "slave"):
            raise ConfigError(
                f"unknown link option {key!r} (addresses, baud, lines, name, names, slave)"
            )
        data[key] = value
    return link_from_mapping(data, devices)


@dataclass(slots=True)
class FileConfig:
    host: str | None
    port: int | None
    links: list[LinkSpec]


def load_config_file(path: Path, devices: LinkRulesSource) -> FileConfig:
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from exc
    links = [link_from_mapping(table, devices) for table in data.get("link", [])]
    port = data.get("port")
    return FileConfig(
        host=data.get("host"),
        port=_int("port", port, 1, 65535) if port is not None else None,
        links=links,
    )
