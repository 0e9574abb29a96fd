"""A serial link's ``Link`` face is its engine's (``link.engine.engine_face``): every
member reads the engine's current value, and a member declared under another member's
name fails when the class is defined instead of reading the wrong value."""

from __future__ import annotations

import pytest

from servotune.devices.slap2.link import Slap2Link, Slap2LinkConfig
from servotune.devices.z1100.link import Z1100Link, Z1100LinkConfig
from servotune.link.base import HasCounters, HasWireBusy, Link, WireStats
from servotune.link.engine import LinkEngine, engine_face
from servotune.transports.serial import SerialConnector
from tests.support.sink import RecordingSink


def links() -> list[Slap2Link | Z1100Link]:
    sink = RecordingSink()
    return [
        Slap2Link(
            Slap2LinkConfig("line", "/dev/null", [0, 1], baud=9600),
            SerialConnector("/dev/null", 9600),
            sink,
            clock=lambda: 12.5,
        ),
        Z1100Link(
            Z1100LinkConfig("chip", "/dev/null", baud=4800),
            SerialConnector("/dev/null", 4800),
            sink,
            clock=lambda: 12.5,
        ),
    ]


@pytest.mark.parametrize("link", links(), ids=lambda link: link.device)
def test_the_face_reads_the_engine_now(link: Slap2Link | Z1100Link) -> None:
    engine = link.engine
    assert (link.id, link.path, link.baud) == (engine.id, engine.path, engine.baud)
    assert link.state == "connecting"
    engine.set_state("error", "a test")
    engine.add_error()
    engine.count("retries", 2)
    assert link.state == "error"
    assert link.errors == engine.errors == 1
    assert link.counters == engine.counters and link.counters["retries"] == 2
    assert link.wire_busy is None  # no channel open
    assert link.now() == 12.5
    assert link.run.__self__ is engine  # type: ignore[attr-defined]
    assert isinstance(link, HasCounters | HasWireBusy | WireStats)
    face: Link = link
    assert face.axes and face.device in ("slap2", "z1100")


def test_a_name_out_of_order_fails_when_the_class_is_defined() -> None:
    with pytest.raises(RuntimeError) as info:

        class Misnamed:
            id, baud, path, state, errors, counters, wire_busy, now, run = engine_face()

            @property
            def engine(self) -> LinkEngine:
                raise AssertionError("never read")

    assert isinstance(info.value.__cause__, TypeError)
    assert "Misnamed.baud would read the engine's path" in str(info.value.__cause__)
