"""``servotune perf`` and its former name ``servotune bench``: one command, two names.

Users' scripts call ``servotune bench``; both names must parse the same arguments to the
same handler and check the same things.
"""

from __future__ import annotations

import pytest

from servotune.cli import build_parser, cmd_perf, main


@pytest.mark.parametrize("name", ["perf", "bench"])
def test_both_names_parse_to_the_perf_command(name: str) -> None:
    parser = build_parser()
    demo = parser.parse_args([name, "demo", "--seconds", "3", "--hog", "off"])
    assert demo.func is cmd_perf
    assert (demo.device, demo.seconds, demo.hog) == ("demo", 3.0, "off")
    device = parser.parse_args([name, "slap2", "--baud", "19200", "--addresses", "0,1"])
    assert device.func is cmd_perf
    assert (device.device, device.baud, device.addresses) == ("slap2", 19200, [0, 1])
    assert device.subparser.prog == f"servotune {name}"  # errors name what the user typed


@pytest.mark.parametrize("name", ["perf", "bench"])
def test_both_names_refuse_a_bad_device_or_address(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as refused:
        build_parser().parse_args([name, "nosuchdevice"])
    assert refused.value.code == 2
    assert "invalid choice: 'nosuchdevice'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:
        main([name, "slap2", "--addresses", "0,16"])  # SLAP2 modules are 0..15
    assert refused.value.code == 2
    err = capsys.readouterr().err
    assert f"servotune {name}: error: argument --addresses" in err and "0..15" in err
