"""Link specs and config files: what `servotune serve --link ...` accepts and refuses."""

from __future__ import annotations

from pathlib import Path

import pytest

from servotune.config import ConfigError, load_config_file, parse_link_spec


def test_link_spec_from_the_readme() -> None:
    spec = parse_link_spec("slap2:/dev/ttyUSB0?addresses=0,1&baud=19200&lines=512")
    assert spec.device == "slap2"
    assert spec.path == "/dev/ttyUSB0"
    assert spec.addresses == [0, 1]
    assert spec.baud == 19200
    assert spec.lines == 512
    assert spec.link_id == "slap2-ttyUSB0"


def test_link_spec_defaults_and_names() -> None:
    spec = parse_link_spec("slap2:/tmp/ttySIM?name=bench&names=Lift,Gripper&addresses=3,4")
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
        parse_link_spec(spec)


def test_toml_config(tmp_path: Path) -> None:
    path = tmp_path / "servotune.toml"
    path.write_text(
        'port = 8100\n[[link]]\ndevice = "slap2"\npath = "/dev/ttyUSB1"\n'
        "addresses = [0, 2]\nlines = 1000\n"
    )
    config = load_config_file(path)
    assert config.port == 8100
    assert config.links[0].addresses == [0, 2]
    assert config.links[0].lines == 1000
