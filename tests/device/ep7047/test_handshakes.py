"""The EP7047-1032 command handshakes without a thread, a master or a simulator: requests,
inputs and times in, outputs and reports out (``devices.ep7047.handshakes.Handshakes``)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest

from servotune.devices.ep7047 import codec
from servotune.devices.ep7047.codec import (
    Inputs,
    PosControl,
    PosDiag,
    PosStatus,
    SdoObject,
    StartType,
    StmControl,
    StmStatus,
)
from servotune.devices.ep7047.handshakes import Handshakes
from servotune.devices.ep7047.requests import CycleCounters, RequestQueue, _Exec, _Kind, _Request
from servotune.link.base import DeviceRefusedError
from servotune.schema import EventLevel

CYCLE_S = 0.002
READY = Inputs(stm_status=StmStatus.READY_TO_ENABLE | StmStatus.READY)


@dataclass
class Reports:
    """Records what the handshakes report (``HandshakeReports``)."""

    events: list[tuple[EventLevel, str, bool]] = field(default_factory=list)
    results: dict[int, object] = field(default_factory=dict)
    errors: dict[int, BaseException] = field(default_factory=dict)

    def post_event(self, level: EventLevel, message: str, *, axis: bool = True) -> None:
        self.events.append((level, message, axis))

    def resolve(self, request: _Request, result: object = None) -> None:
        self.results[id(request)] = result

    def reject(self, request: _Request, error: BaseException) -> None:
        self.errors[id(request)] = error


@dataclass
class Bench:
    handshakes: Handshakes
    queue: RequestQueue
    reports: Reports
    coe: dict[SdoObject, int]
    counters: CycleCounters
    loop: asyncio.AbstractEventLoop

    def request(self, kind: _Kind, **values: Any) -> _Request:
        request = _Request(kind, self.loop.create_future(), **values)
        self.queue.put(request)
        return request

    def cycle(self, inputs: Inputs, now: float) -> None:
        """One cycle as ``Cycle._cycle_steps`` runs it, without the SDO slot."""
        hs = self.handshakes
        if self.queue.urgent:
            hs.take_urgent(now)
        cs = hs.state
        if cs.pending is not None or cs.exec_state is _Exec.ARMING:
            hs.before_exchange(now)
        if cs.pending is None and cs.sdo_job is None and self.queue.normal:
            hs.take_normal(now)
        cs.inputs = inputs
        if cs.after_exchange:
            for request in cs.after_exchange:
                self.reports.resolve(request, "sent")
            cs.after_exchange.clear()
        hs.advance_stop(inputs, now)
        hs.advance_exec(inputs, now)
        hs.advance_pending(inputs, now)

    def outputs(self) -> tuple[StmControl, PosControl]:
        out = self.handshakes.state.outputs()
        return out.stm_control, out.pos_control


@pytest.fixture
def bench() -> Iterator[Bench]:
    loop = asyncio.new_event_loop()
    queue, reports, counters = RequestQueue(), Reports(), CycleCounters()
    coe: dict[SdoObject, int] = {codec.EMERGENCY_DECELERATION: 100}
    handshakes = Handshakes(
        cycle_s=CYCLE_S, queue=queue, reports=reports, coe=coe, counters=counters
    )
    try:
        yield Bench(handshakes, queue, reports, coe, counters, loop)
    finally:
        loop.close()


def enabled(bench: Bench, now: float = 0.0) -> None:
    request = bench.request(_Kind.ENABLE)
    bench.cycle(Inputs(), now)
    assert bench.outputs()[0] & StmControl.ENABLE
    bench.cycle(READY, now + CYCLE_S)
    assert bench.reports.results[id(request)] == "enabled"


def test_enable_waits_for_stm_ready(bench: Bench) -> None:
    request = bench.request(_Kind.ENABLE)
    bench.cycle(Inputs(), 0.0)
    assert bench.outputs() == (StmControl.ENABLE, PosControl.NONE)
    bench.cycle(Inputs(), 0.4)
    assert id(request) not in bench.reports.results
    bench.cycle(READY, 0.41)
    assert bench.reports.results[id(request)] == "enabled"
    assert bench.handshakes.state.pending is None


def test_enable_without_ready_is_refused_and_dropped(bench: Bench) -> None:
    request = bench.request(_Kind.ENABLE)
    bench.cycle(Inputs(), 0.0)
    bench.cycle(Inputs(), 0.51)
    error = bench.reports.errors[id(request)]
    assert isinstance(error, DeviceRefusedError) and "STM Ready" in str(error)
    assert bench.outputs() == (StmControl.NONE, PosControl.NONE)


def test_start_raises_execute_a_cycle_later_and_holds_it_until_busy_falls(bench: Bench) -> None:
    enabled(bench)
    move = bench.request(_Kind.START, start_type=StartType.ABSOLUTE, target=4096, velocity_bp=1000)
    bench.cycle(READY, 0.01)  # parameters written, Execute still low
    out = bench.handshakes.state.outputs()
    assert out.target_position_counts == 4096 and not out.pos_control & PosControl.EXECUTE
    busy = Inputs(stm_status=READY.stm_status, pos_status=PosStatus.BUSY)
    bench.cycle(busy, 0.012)
    assert bench.outputs()[1] & PosControl.EXECUTE
    bench.cycle(busy, 0.014)
    assert bench.reports.results[id(move)] == "ABSOLUTE started"
    bench.cycle(busy, 0.5)
    assert bench.outputs()[1] & PosControl.EXECUTE, "Execute is held while Busy"
    done = Inputs(
        stm_status=READY.stm_status,
        pos_status=PosStatus.IN_TARGET,
        actual_position_counts=4096,
    )
    bench.cycle(done, 0.6)
    assert not bench.outputs()[1] & PosControl.EXECUTE
    level, text, _ = bench.reports.events[-1]
    assert level == "info" and "ABSOLUTE ended at 4096 counts" in text and "In-Target" in text


def test_start_while_not_enabled_is_refused_before_anything_is_sent(bench: Bench) -> None:
    move = bench.request(_Kind.START, start_type=StartType.ABSOLUTE, target=10)
    bench.cycle(Inputs(), 0.0)
    assert "not enabled" in str(bench.reports.errors[id(move)])
    assert bench.handshakes.state.outputs() == codec.Outputs()


def test_stop_discards_queued_commands_keeps_sdo_and_drops_enable_at_standstill(
    bench: Bench,
) -> None:
    enabled(bench)
    moving = Inputs(stm_status=READY.stm_status, pos_status=PosStatus.BUSY, actual_velocity_bp=500)
    bench.request(_Kind.START, start_type=StartType.ENDLESS_PLUS, velocity_bp=500)
    bench.cycle(READY, 0.01)
    bench.cycle(moving, 0.012)
    bench.cycle(moving, 0.014)
    queued_move = bench.request(_Kind.START, start_type=StartType.ABSOLUTE, target=0)
    sdo = bench.request(_Kind.SDO_READ, obj=codec.DRIVE_STATE)
    stop = bench.request(_Kind.STOP)
    bench.cycle(moving, 0.02)
    assert bench.outputs() == (StmControl.ENABLE, PosControl.EMERGENCY_STOP)
    assert bench.reports.results[id(stop)] == "sent"
    assert "STOP came first" in str(bench.reports.errors[id(queued_move)])
    assert list(bench.queue.normal) == [sdo] or bench.handshakes.state.sdo_job is sdo
    bench.cycle(moving, 0.022)
    bench.cycle(moving, 0.024)
    assert bench.outputs()[0] & StmControl.ENABLE, "Enable is kept while the drive ramps down"
    still = Inputs(stm_status=READY.stm_status, actual_position_counts=1234)
    bench.cycle(still, 0.03)
    assert bench.outputs() == (StmControl.NONE, PosControl.NONE)
    assert ("warning", "STOP: stopped at 1234 counts, Enable off", True) in bench.reports.events


def test_stop_without_standstill_drops_enable_after_the_emergency_ramp(bench: Bench) -> None:
    enabled(bench)
    bench.request(_Kind.STOP)
    moving = Inputs(stm_status=READY.stm_status, actual_velocity_bp=500)
    bench.cycle(moving, 1.0)
    for step in range(1, 5):
        bench.cycle(moving, 1.0 + step * CYCLE_S)
    assert bench.outputs()[0] & StmControl.ENABLE
    bench.cycle(moving, 1.0 + 0.1 + 0.5 + CYCLE_S)  # emergency deceleration 100 ms + 0.5 s
    assert bench.outputs() == (StmControl.NONE, PosControl.NONE)


def test_drop_outputs_after_a_stall_refuses_the_pending_command_and_counts_it(
    bench: Bench,
) -> None:
    bench.handshakes.drop_outputs(0.2, 0.1)  # nothing asserted: nothing to drop or say
    assert bench.counters.watchdog_trips == 0 and not bench.reports.events
    request = bench.request(_Kind.ENABLE)
    bench.cycle(Inputs(), 0.0)
    bench.handshakes.drop_outputs(0.2, 0.1)
    assert bench.outputs() == (StmControl.NONE, PosControl.NONE)
    assert "dropped it" in str(bench.reports.errors[id(request)])
    assert (bench.counters.watchdog_trips, bench.counters.errors) == (1, 1)
    level, text, _ = bench.reports.events[-1]
    assert level == "error" and "no good process data for 200 ms" in text


def test_diagnosis_is_read_when_warning_rises_and_cleared_when_it_falls(bench: Bench) -> None:
    hs = bench.handshakes
    warning = Inputs(pos_status=PosStatus.WARNING)
    assert hs.diag_due(Inputs(), warning, 1.0)
    hs.take_diag(int(PosDiag.COMMAND_REJECTED) | 0x100, 1.0)  # bits above :03 are not it
    assert hs.state.diag is PosDiag.COMMAND_REJECTED
    assert not hs.diag_due(warning, warning, 1.05)
    assert hs.diag_due(warning, warning, 1.2), "re-read after 0.1 s"
    assert not hs.diag_due(warning, Inputs(), 1.3)
    assert hs.state.diag is PosDiag.NONE
