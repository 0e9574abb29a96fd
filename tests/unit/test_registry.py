"""The device registry: one entry per device, consistent with itself, read lazily."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest
from pydantic import ValidationError

from servotune.autotune.session import IdentifyRequest
from servotune.config import parse_link_spec
from servotune.devices import default_registry
from servotune.devices.slap2.codec import PWM_MAX as SLAP2_PWM_MAX
from servotune.devices.z1100.law import PWM_FULL_SCALE as Z1100_PWM_FULL_SCALE
from servotune.tuning.plants import OUTPUT_FULL_SCALE

DEVICES = default_registry()


def test_each_entry_is_consistent() -> None:
    assert DEVICES.names() == ("slap2", "z1100", "ep7047")
    assert default_registry() is not DEVICES  # a fresh registry per composition root
    for entry in DEVICES:
        # the example in an entry's error messages is a link spec of that device
        assert parse_link_spec(entry.link_rules.example, DEVICES).device == entry.name
        for module in entry.compute_modules:
            importlib.import_module(module)
        law = DEVICES.law(entry.name)
        assert (law is None) == (entry.law is None)
        assert law is None or law.device == entry.name
    assert DEVICES.law("ep7047") is None and DEVICES.law("modbus") is None
    assert DEVICES.law("slap2") is DEVICES.law("slap2")  # loaded once per registry
    assert [e.name for e in DEVICES.simulated(pty=True)] == ["slap2", "z1100"]
    assert [e.name for e in DEVICES.simulated()] == ["slap2", "z1100", "ep7047"]
    assert DEVICES.tuned() == ("gräbner SLAP2", "CNC Designer Z1100")


def test_each_stop_rig_has_its_cases_named_once() -> None:
    # perf.stops takes its cases from here: a device with a stop rig says what to stop.
    for entry in DEVICES:
        simulator = entry.simulator
        assert simulator is not None
        assert bool(simulator.stop_cases) == (simulator.stop_rig is not None), entry.name
        names = [case.name for case in simulator.stop_cases]
        assert len(set(names)) == len(names), names
        assert {case.state for case in simulator.stop_cases} == {"top speed", "limit cycle"} or (
            entry.name == "ep7047"  # a stepper drive: no loop of its own to oscillate
        )


def test_the_auto_tunes_pwm_bound_is_each_tuned_devices_full_scale() -> None:
    """``max_pwm`` is bounded by the generic ``OUTPUT_FULL_SCALE``: the PWM full scale
    of both tuned devices, so the API accepts exactly what either device can apply."""
    assert OUTPUT_FULL_SCALE == SLAP2_PWM_MAX == Z1100_PWM_FULL_SCALE
    IdentifyRequest(max_pwm=OUTPUT_FULL_SCALE, max_distance_counts=4000)
    with pytest.raises(ValidationError, match="max_pwm"):
        IdentifyRequest(max_pwm=OUTPUT_FULL_SCALE + 1, max_distance_counts=4000)


def test_the_cli_reads_the_registry_without_loading_links_laws_or_numpy() -> None:
    # Every command builds the parser from the registry: `servotune sim` and `--help`
    # must not pay for the links, laws and tuners.
    code = (
        "import sys, servotune.cli as c; c.build_parser(); "
        "print(sorted(m for m in sys.modules if m.startswith('servotune.devices.') "
        "and m.rsplit('.', 1)[1] in ('link', 'law', 'tuner', 'gain_rule')), "
        "'numpy' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert out.strip() == "[] False", out


def test_the_poll_sets_servotune_bench_prints() -> None:
    from servotune.config import LinkSpec
    from servotune.perf.link_rate import _CountingSink

    def poll_set(spec: LinkSpec) -> tuple[str, float]:
        simulator = DEVICES.get(spec.device).simulator
        assert simulator is not None and simulator.poll_set is not None
        found = simulator.poll_set(DEVICES.build_link(spec, _CountingSink()))
        return found.description, found.turns_per_sample

    # SLAP2: (rp + pe + rss, each character and the CR a turn) + rve every 8th cycle
    # + the se0 re-selection between two modules, for each module
    text, turns = poll_set(LinkSpec("slap2", "/dev/null", "line", 19200, [0, 1]))
    assert text.startswith("SLAP2 19200 baud, 2 module(s) on one line, poll set rp+pe+rss")
    assert turns == (10 + 4 / 8 + 4) * 2
    text, turns = poll_set(LinkSpec("z1100", "/dev/null", "chip", 9600, [0, 1, 2]))
    assert text.startswith("Z1100 9600 baud, 3 axes") and turns == 6 + 3 / 4
