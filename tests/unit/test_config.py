"""Link specs and config files: what `servotune serve --link ...` accepts and refuses."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from servotune.config import ConfigError, LinkRules, LinkSpec, load_config_file, parse_link_spec
from servotune.devices import default_registry

DEVICES = default_registry()


def test_link_spec_from_the_readme() -> None:
    spec = parse_link_spec("slap2:/dev/ttyUSB0?addresses=0,1&baud=19200&lines=512", DEVICES)
    assert spec.device == "slap2"
    assert spec.path == "/dev/ttyUSB0"
    assert spec.addresses == [0, 1]
    assert spec.baud == 19200
    assert spec.lines == 512
    assert spec.link_id == "slap2-ttyUSB0"


def test_link_spec_defaults_and_names() -> None:
    spec = parse_link_spec("slap2:/tmp/ttySIM?name=bench&names=Lift,Gripper&addresses=3,4", DEVICES)
    assert spec.link_id == "bench"
    assert spec.names == {3: "Lift", 4: "Gripper"}
    assert spec.baud == 19200


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("/dev/ttyUSB0", "link spec must look like"),
        ("modbus:/dev/ttyUSB0", "device must be one of"),
        ("slap2:/dev/ttyUSB0?addresses=16", "addresses must be in 0..15"),
        ("slap2:/dev/ttyUSB0?addresses=1,1", "distinct"),
        ("slap2:/dev/ttyUSB0?baud=12345", "baud must be one of"),
        ("slap2:/dev/ttyUSB0?lines=zero", "lines must be an integer"),
        ("slap2:/dev/ttyUSB0?speed=1", "unknown link option 'speed'"),
    ],
)
def test_bad_link_specs_name_the_field(spec: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_link_spec(spec, DEVICES)


def test_toml_config(tmp_path: Path) -> None:
    path = tmp_path / "servotune.toml"
    path.write_text(
        'port = 8100\n[[link]]\ndevice = "slap2"\npath = "/dev/ttyUSB1"\n'
        "addresses = [0, 2]\nlines = 1000\n"
    )
    config = load_config_file(path, DEVICES)
    assert config.port == 8100
    assert config.links[0].addresses == [0, 2]
    assert config.links[0].lines == 1000


def test_each_devices_rules_apply() -> None:
    # addressing "fixed": one chip, three motors, whatever is asked (still range-checked)
    z1100 = parse_link_spec("z1100:/dev/ttyUSB0?addresses=4", DEVICES)
    assert (z1100.addresses, z1100.baud) == ([0, 1, 2], 9600)
    with pytest.raises(ConfigError, match=re.escape("addresses must be in 0..15")):
        parse_link_spec("z1100:/dev/ttyUSB0?addresses=16", DEVICES)
    # addressing "slave": the position on the EtherCAT bus, no baud rate
    ep7047 = parse_link_spec("ep7047:eth0?slave=3&name=ec", DEVICES)
    assert (ep7047.addresses, ep7047.baud, ep7047.link_id) == ([3], 0, "ec")
    assert parse_link_spec("ep7047:eth0", DEVICES).addresses == [1]
    with pytest.raises(ConfigError, match=re.escape("slave must be in 1..65535, got 0")):
        parse_link_spec("ep7047:eth0?slave=0", DEVICES)


def test_the_devices_and_their_rules_come_from_the_registry() -> None:
    assert "device must be one of slap2, z1100, ep7047, got 'modbus'" in _refusal("modbus:/x")
    rules = LinkRules(default_baud=9600, address_range=(1, 3), example="fake:/dev/ttyS0")
    fake = dataclasses.replace(DEVICES.get("slap2"), name="fake", link_rules=rules)
    devices = DEVICES.with_devices(fake)
    spec = parse_link_spec("fake:/dev/ttyS1?addresses=1,3", devices)
    assert spec == LinkSpec("fake", "/dev/ttyS1", "fake-ttyS1", 9600, [1, 3], 512, {})
    with pytest.raises(ConfigError, match=re.escape("addresses must be in 1..3, got 0")):
        parse_link_spec("fake:/dev/ttyS1?addresses=0", devices)
    with pytest.raises(ConfigError, match="device must be one of slap2, z1100, ep7047, fake"):
        parse_link_spec("modbus:/x", devices)
    with pytest.raises(ValueError, match="'fake' is registered twice"):
        devices.with_devices(fake)
    with pytest.raises(KeyError, match="unknown device 'modbus'"):
        devices.get("modbus")


def _refusal(spec: str) -> str:
    with pytest.raises(ConfigError) as caught:
        parse_link_spec(spec, DEVICES)
    return str(caught.value)
