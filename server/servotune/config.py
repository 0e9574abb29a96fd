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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl

DEVICES = ("slap2", "z1100", "ep7047")
DEFAULT_BAUD = {"slap2": 19200, "z1100": 9600, "ep7047": 0}
# ``ep7047:sim`` runs the simulated slave in-process instead of a NIC (demo, trials).
SIMULATED_NIC = "sim"
BAUD_RATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)


class ConfigError(ValueError):
    """A link spec or config file that cannot be used; the message names the field."""


@dataclass(slots=True)
class LinkSpec:
    device: str
    path: str
    link_id: str
    baud: int = 19200
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


def link_from_mapping(data: dict[str, Any]) -> LinkSpec:
    """Build and check a LinkSpec from a dict (TOML table or parsed link spec)."""
    device = str(data.get("device", ""))
    if device not in DEVICES:
        raise ConfigError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    path = str(data.get("path", ""))
    if not path:
        raise ConfigError("path is missing (e.g. /dev/ttyUSB0)")
    if device == "ep7047":
        baud = 0  # EtherCAT: no baud rate
    else:
        baud = _int("baud", data.get("baud", DEFAULT_BAUD[device]), 300, 1_000_000)
        if baud not in BAUD_RATES:
            raise ConfigError(f"baud must be one of {', '.join(map(str, BAUD_RATES))}, got {baud}")
    raw_addresses = data.get("addresses", [0])
    if isinstance(raw_addresses, str):
        raw_addresses = [a for a in raw_addresses.split(",") if a.strip()]
    addresses = [_int("addresses", a, 0, 15) for a in raw_addresses]
    if device == "z1100":
        addresses = [0, 1, 2]  # one chip, three motors: there is nothing to address
    if device == "ep7047":
        # The slave's position on the bus (1 = first slave after the master).
        addresses = [_int("slave", data.get("slave", 1), 1, 65535)]
    if not addresses or len(set(addresses)) != len(addresses):
        raise ConfigError("addresses must list distinct module addresses 0..15")
    lines = _int("lines", data.get("lines", 512), 1, 1_000_000)
    raw_names = data.get("names", [])
    if isinstance(raw_names, str):
        raw_names = raw_names.split(",")
    names = {a: str(n) for a, n in zip(addresses, raw_names, strict=False) if str(n).strip()}
    link_id = str(data.get("name") or _link_id_from_path(device, path))
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", link_id):
        raise ConfigError(f"name may use letters, digits, '-', '_' and '.', got {link_id!r}")
    return LinkSpec(device, path, link_id, baud, addresses, lines, names)


def parse_link_spec(spec: str) -> LinkSpec:
    """Parse ``device:path?key=value&...``."""
    device, sep, rest = spec.partition(":")
    if not sep:
        raise ConfigError(
            f"link spec must look like 'slap2:/dev/ttyUSB0?addresses=0,1', got {spec!r}"
        )
    path, _, query = rest.partition("?")
    data: dict[str, Any] = {"device": device, "path": path}
    for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=False):
        if key not in ("addresses", "baud", "lines", "name", "names", "slave"):
            raise ConfigError(
                f"unknown link option {key!r} (addresses, baud, lines, name, names, slave)"
            )
        data[key] = value
    return link_from_mapping(data)


@dataclass(slots=True)
class FileConfig:
    host: str | None
    port: int | None
    links: list[LinkSpec]


def load_config_file(path: Path) -> FileConfig:
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from exc
    links = [link_from_mapping(table) for table in data.get("link", [])]
    port = data.get("port")
    return FileConfig(
        host=data.get("host"),
        port=_int("port", port, 1, 65535) if port is not None else None,
        links=links,
    )
