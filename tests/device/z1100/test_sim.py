"""Z1100 simulator: driven with request bytes and simulation time (no pty, except the last
test, which goes through a real pseudo-terminal with pyserial at 9600 baud)."""

from __future__ import annotations

import itertools
import json
from collections.abc import Callable, Iterable
from pathlib import Path

import pytest

from servotune.devices.z1100 import codec
from servotune.devices.z1100.codec import (
    Cab,
    Command,
    Gains,
    Job,
    ReplyCode,
    StartStatus,
    StopStatus,
)
from servotune.devices.z1100.sim.chip import Z1100Chip
from servotune.devices.z1100.sim.servo import AxisHardware
from servotune.sim.base import PowerCyclable, SimDevice

BYTE_S = 10 / 9600  # one character at 9600 8N1
HEAVY_KG_M2 = 7.6e-6  # 20 x the rotor inertia
GOOD_LIGHT = (32, 16, 8)  # gains that suit an unloaded motor at Stm = 1


class Bench:
    """A host on the chip's line: sends packets byte by byte at 9600 baud, runs time."""

    def __init__(self, chip: Z1100Chip) -> None:
        self.chip = chip
        self.t = chip.time_s
        self.unsolicited = bytearray()

    def send(self, data: bytes) -> bytes:
        out = bytearray()
        for byte in data:
            self.t += BYTE_S
            self.unsolicited += self.chip.advance_to(self.t)
            out += self.chip.receive(byte)
        return bytes(out)

    def tx(self, request: codec.Request) -> codec.Reply:
        out = self.send(request.encode())
        assert len(out) == codec.REPLY_SIZE, out.hex(" ")
        return codec.decode_reply(out)

    def ok(self, request: codec.Request) -> codec.Reply:
        reply = self.tx(request)
        assert reply.executed, reply.error_message()
        return reply

    def get(self, command: Command, axis: int | None = None) -> codec.GetValue:
        return codec.decode_get(command, self.ok(codec.make_get(command, axis)).data)

    def run(self, seconds: float, *, step_s: float = 0.001) -> bytes:
        end = self.t + seconds
        out = bytearray()
        while self.t < end - 1e-12:
            self.t = min(self.t + step_s, end)
            out += self.chip.advance_to(self.t)
        return bytes(out)

    def run_until(
        self, condition: Callable[[], bool], timeout_s: float, *, step_s: float = 0.001
    ) -> float:
        """Run until ``condition``; returns the time it took (fails on timeout)."""
        start = self.t
        while not condition():
            assert self.t - start < timeout_s, "condition not reached in time"
            self.run(step_s, step_s=step_s)
        return self.t - start

    def watch(
        self, seconds: float, probe: Callable[[], float], *, step_s: float = 0.0005
    ) -> list[float]:
        values = []
        end = self.t + seconds
        while self.t < end:
            self.run(step_s, step_s=step_s)
            values.append(probe())
        return values

    def configure(
        self,
        axis: int,
        gains: tuple[int, int, int] = GOOD_LIGHT,
        *,
        vmax: int = 100_000,
        acc: int = 1_000_000,
        limit: int = 2000,
        hvm: int = 20_000,
        hac: int = 200_000,
        job: Job = Job.TARGET,
        busy: bool = False,
    ) -> None:
        for request in (
            codec.make_set_kab(axis, *gains),
            codec.make_set_vmax(axis, vmax),
            codec.make_set_acc(axis, acc),
            codec.make_set_limit(axis, limit),
            codec.make_set_hvm(axis, hvm),
            codec.make_set_hac(axis, hac),
            codec.make_set_busy(axis, busy),
            codec.make_set_job(axis, job),
        ):
            self.ok(request)

    def running(self) -> frozenset[int]:
        status = self.get(Command.GET_START)
        assert isinstance(status, StartStatus)
        return status.running

    def move(self, axis: int, target: int, timeout_s: float = 2.0) -> float:
        self.ok(codec.make_set_target(axis, target))
        self.ok(codec.make_start([axis]))
        assert axis in self.running()
        return self.run_until(lambda: not self.chip.axis_state(axis).running, timeout_s)

    def encoder(self, axis: int) -> int:
        value = self.get(Command.GET_ENCODER, axis)
        assert isinstance(value, int)
        return value


@pytest.fixture
def bench() -> Bench:
    return Bench(Z1100Chip())


def peak_to_peak(values: Iterable[float]) -> float:
    items = list(values)
    return max(items) - min(items)


# --- the contract ---------------------------------------------------------------------


def test_chip_is_a_sim_device_that_can_be_power_cycled() -> None:
    chip = Z1100Chip()
    assert isinstance(chip, SimDevice)
    assert isinstance(chip, PowerCyclable)
    assert chip.advance_to(0.5) == b""
    assert chip.advance_to(0.1) == b""  # time never runs backwards
    assert chip.time_s == 0.5


def test_the_chip_never_talks_unasked(bench: Bench) -> None:
    bench.configure(0)
    assert bench.run(0.3) == b""
    assert bench.send(b"\x00\x13\xff") == b""  # garbage between packets is ignored


# --- every command answers as documented ------------------------------------------------

WRITES = [
    (codec.make_set_kab(1, 10, 20, 30), Command.GET_KABH, 1, Gains(10, 20, 30)),
    (codec.make_set_kab(2, 5, 6, 7, moving=False), Command.GET_KABD, 2, Gains(5, 6, 7)),
    (codec.make_set_vmax(0, 12_345), Command.GET_VMAX, 0, 12_345),
    (codec.make_set_acc(1, 54_321), Command.GET_ACC, 1, 54_321),
    (codec.make_set_stm(2, 7), Command.GET_STM, 2, 7),
    (codec.make_set_hvm(0, 999), Command.GET_HVM, 0, 999),
    (codec.make_set_hac(1, 888), Command.GET_HAC, 1, 888),
    (codec.make_set_limit(2, 16_383), Command.GET_LIMIT, 2, 16_383),
    (codec.make_set_cab(0, Cab(7)), Command.GET_CAB, 0, Cab(7)),
    (codec.make_set_job(1, Job.VELOCITY), Command.GET_JOB, 1, Job.VELOCITY),
    (codec.make_set_busy(2, True), Command.GET_BUSY, 2, True),
    (codec.make_set_target(0, -123_456), Command.GET_TARGET, 0, -123_456),
]


@pytest.mark.parametrize(("write", "read", "axis", "value"), WRITES)
def test_set_then_get_reads_back(
    bench: Bench, write: codec.Request, read: Command, axis: int, value: object
) -> None:
    reply = bench.tx(write)
    assert reply.code == ReplyCode.OK and reply.data == 0
    assert bench.get(read, axis) == value
    # the other axes are untouched
    for other in {0, 1, 2} - {axis}:
        assert bench.get(read, other) != value


def test_reads_of_a_chip_at_rest(bench: Bench) -> None:
    for axis in range(3):
        assert bench.get(Command.GET_ENCODER, axis) == 0
        assert bench.get(Command.GET_ERROR, axis) == 0
        assert bench.get(Command.GET_SWITCH, axis) is False
        assert bench.get(Command.GET_STM, axis) == 1  # the manual's power-on value
        assert bench.get(Command.GET_JOB, axis) is Job.FREE
    assert bench.get(Command.GET_START) == StartStatus()
    assert bench.get(Command.GET_STOP) == StopStatus()
    assert bench.get(Command.GET_ESTOP) == StopStatus()


@pytest.mark.parametrize("byte", [0x03, 0x1F, 0x31, 0x3D, 0x4C, 0x80 | 0x48, 0xC3, 0xC7, 0xFF])
def test_unknown_commands_set_bit_1(bench: Bench, byte: int) -> None:
    reply = bench.tx(codec.Request(byte, 1234))
    assert reply.code == ReplyCode.UNKNOWN_COMMAND
    assert reply.error_message() == "unknown command"


def test_the_fence_is_answered_as_unknown_and_changes_nothing(bench: Bench) -> None:
    before = bench.get(Command.GET_VMAX, 0)
    assert codec.is_fence_reply(bench.tx(codec.make_fence()))
    assert bench.get(Command.GET_VMAX, 0) == before


def test_bad_checksum_sets_bit_0_and_executes_nothing(bench: Bench) -> None:
    packet = bytearray(codec.make_set_vmax(0, 5000).encode())
    packet[6] ^= 0x01
    out = bench.send(bytes(packet))
    reply = codec.decode_reply(out)
    assert reply.code == ReplyCode.CHECKSUM and not reply.executed
    assert bench.get(Command.GET_VMAX, 0) == 0  # and the chip is still in step


def test_incomplete_packet_times_out_after_100_ms_with_bit_2(bench: Bench) -> None:
    bench.send(codec.make_get_kab(0).encode()[:3])
    assert bench.run(0.095) == b""
    out = bench.run(0.010)  # the deadline is 100 ms after the first byte
    reply = codec.decode_reply(out)
    assert reply.code == ReplyCode.TIMEOUT
    assert "100 ms" in (reply.error_message() or "")
    # the discarded bytes do not spoil the next packet
    bench.ok(codec.make_set_vmax(0, 777))
    assert bench.get(Command.GET_VMAX, 0) == 777


def test_noise_makes_the_chip_send_an_unsolicited_reply(bench: Bench) -> None:
    bench.chip.inject_noise_reply()
    out = bench.run(0.001)
    (reply,) = codec.ReplyDecoder().feed(out)
    assert reply.code == ReplyCode.COMMUNICATION and not reply.executed
    assert "communication error" in (reply.error_message() or "")


# --- motion ------------------------------------------------------------------------------


def test_move_reaches_the_target_on_a_trapezoid_and_busy_follows(bench: Bench) -> None:
    bench.configure(0, busy=True)
    assert bench.chip.busy_pin == 1
    bench.ok(codec.make_set_target(0, 20_000))
    bench.ok(codec.make_start([0]))
    assert bench.chip.busy_pin == 0
    assert bench.running() == {0}
    took_s = bench.run_until(lambda: bench.chip.axis_state(0).running is False, 1.0)
    # 20000 counts at 100000 counts/s, 1e6 counts/s^2: 0.1 s up, 0.1 s cruise, 0.1 s down
    assert took_s == pytest.approx(0.3, abs=0.01)
    assert bench.chip.busy_pin == 1
    assert bench.running() == frozenset()  # the start bit cleared itself
    bench.run(0.05)
    assert abs(bench.encoder(0) - 20_000) <= 2
    assert abs(bench.get(Command.GET_ERROR, 0)) <= 2  # type: ignore[arg-type]


def _peak_profile_speed(bench: Bench, axis: int, target: int) -> tuple[float, float]:
    bench.ok(codec.make_set_target(axis, target))
    bench.ok(codec.make_start([axis]))
    step_s = 0.005  # 156.25 samples: a whole number of samples is off by < 1 %
    positions = [bench.chip.axis_state(axis).reference_counts]
    while bench.chip.axis_state(axis).running:
        bench.run(step_s, step_s=step_s)
        positions.append(bench.chip.axis_state(axis).reference_counts)
    speeds = [(b - a) / step_s for a, b in itertools.pairwise(positions)]
    return max(speeds), positions[-1]


def test_short_moves_never_reach_vmax(bench: Bench) -> None:
    bench.configure(0)
    peak_short, end_short = _peak_profile_speed(bench, 0, 2000)
    # sqrt(acc * distance) = sqrt(1e6 * 2000) = 44721 counts/s, well below Vmax (the
    # 5 ms average around the peak of the triangle reads a little lower)
    assert peak_short == pytest.approx(44_721, rel=0.08)
    assert peak_short < 0.5 * 100_000
    assert end_short == 2000
    peak_long, end_long = _peak_profile_speed(bench, 0, 2000 + 30_000)
    assert peak_long == pytest.approx(100_000, rel=0.01)  # cruises at Vmax
    assert end_long == 32_000


def test_two_busy_motors_release_the_pin_when_both_are_done(bench: Bench) -> None:
    bench.configure(0, busy=True)
    bench.configure(1, busy=True)
    bench.configure(2, busy=False)
    bench.ok(codec.make_set_target(0, 2000))
    bench.ok(codec.make_set_target(1, 20_000))
    bench.ok(codec.make_set_target(2, 40_000))
    bench.ok(codec.make_start([0, 1, 2]))
    bench.run_until(lambda: not bench.chip.axis_state(0).running, 1.0)
    assert bench.chip.busy_pin == 0  # motor 2 still moves
    bench.run_until(lambda: not bench.chip.axis_state(1).running, 1.0)
    assert bench.chip.busy_pin == 1  # motor 3 still moves, but does not drive BUSY
    assert bench.chip.axis_state(2).running


def test_start_refuses_a_motor_whose_parameters_are_missing() -> None:
    """The manual: K, A, B, Vmax, Acc, error limit and home speed must be non-zero before
    Start. Decided: the reply is OK (no bit exists), the motor is not started, and
    GetStart shows it."""
    for missing in ("k", "a", "b", "vmax", "acc", "limit", "hvm"):
        bench = Bench(Z1100Chip())
        values = {"vmax": 100_000, "acc": 1_000_000, "limit": 2000, "hvm": 20_000}
        gains = dict(zip("kab", GOOD_LIGHT, strict=True))
        if missing in gains:
            gains[missing] = 0
        else:
            values[missing] = 0
        bench.configure(0, (gains["k"], gains["a"], gains["b"]), **values)
        bench.ok(codec.make_set_target(0, 5000))
        assert bench.ok(codec.make_start([0])).code == ReplyCode.OK
        assert bench.running() == frozenset(), missing
        bench.run(0.05)
        assert abs(bench.encoder(0)) <= 1, missing


def test_start_needs_a_servo_job(bench: Bench) -> None:
    bench.configure(0, job=Job.FREE)
    bench.ok(codec.make_set_target(0, 5000))
    bench.ok(codec.make_start([0]))
    assert bench.running() == frozenset()


# --- forbidden while moving -------------------------------------------------------------

FORBIDDEN = [
    lambda axis: codec.make_set_vmax(axis, 5),
    lambda axis: codec.make_set_acc(axis, 5),
    lambda axis: codec.make_set_hvm(axis, 5),
    lambda axis: codec.make_set_hac(axis, 5),
    lambda axis: codec.make_set_cab(axis, Cab.ENCODER_SWAPPED),
    lambda axis: codec.make_set_job(axis, Job.VELOCITY),
    lambda axis: codec.make_set_target(axis, 5),
    lambda axis: codec.make_start([axis]),
    lambda axis: codec.make_zero(axis),
]


@pytest.mark.parametrize("build", FORBIDDEN)
def test_forbidden_while_the_addressed_motor_moves(
    bench: Bench, build: Callable[[int], codec.Request]
) -> None:
    bench.configure(0)
    bench.configure(1)
    bench.ok(codec.make_set_target(1, 100_000))
    bench.ok(codec.make_start([1]))
    bench.run(0.02)
    reply = bench.tx(build(1))
    assert reply.code == ReplyCode.MOVING_2
    assert reply.error_message() == "forbidden while motor 2 is moving"
    # nothing was executed
    assert bench.get(Command.GET_VMAX, 1) == 100_000
    assert bench.get(Command.GET_ACC, 1) == 1_000_000
    assert bench.get(Command.GET_CAB, 1) == Cab.NONE
    assert bench.get(Command.GET_JOB, 1) is Job.TARGET
    assert bench.get(Command.GET_TARGET, 1) == 100_000
    assert bench.chip.axis_state(1).running and not bench.chip.axis_state(1).homing
    # the same command to a motor at rest is fine while motor 2 moves
    assert bench.tx(build(0)).executed


def test_start_of_a_moving_motor_refuses_the_whole_command(bench: Bench) -> None:
    bench.configure(0)
    bench.configure(1)
    bench.ok(codec.make_set_target(1, 100_000))
    bench.ok(codec.make_start([1]))
    bench.ok(codec.make_set_target(0, 5000))
    assert bench.tx(codec.make_start([0, 1])).code == ReplyCode.MOVING_2
    assert bench.running() == {1}  # motor 1 was not started either


def test_allowed_while_moving_gains_limit_busy_and_job_0(bench: Bench) -> None:
    bench.configure(0)
    bench.ok(codec.make_set_target(0, 100_000))
    bench.ok(codec.make_start([0]))
    bench.run(0.05)
    bench.ok(codec.make_set_kab(0, 40, 16, 8))  # tuning on the fly
    bench.ok(codec.make_set_limit(0, 3000))
    bench.ok(codec.make_set_busy(0, True))
    assert bench.get(Command.GET_KABH, 0) == Gains(40, 16, 8)
    bench.ok(codec.make_set_job(0, Job.FREE))  # power off, even while moving
    assert bench.running() == frozenset()
    assert not bench.chip.axis_state(0).powered
    assert bench.chip.axis_state(0).duty == 0.0


# --- stall protection -------------------------------------------------------------------


def _stall_axis_0(bench: Bench) -> None:
    bench.configure(0, limit=300)
    bench.chip.jam(0)
    bench.ok(codec.make_set_target(0, 20_000))
    bench.ok(codec.make_start([0]))
    bench.run_until(lambda: bench.chip.axis_state(0).stalled, 0.5)


def test_stall_cuts_power_and_flags_bit_7_until_clr(bench: Bench) -> None:
    _stall_axis_0(bench)
    reply = bench.tx(codec.make_get(Command.GET_STOP))
    assert reply.stall and reply.executed  # bit 7 is a flag: the data is valid
    assert codec.unpack_stop(reply.data) == StopStatus(frozenset(), frozenset({0}))
    assert bench.tx(codec.make_get(Command.GET_ESTOP)).data == reply.data
    assert bench.running() == frozenset()
    state = bench.chip.axis_state(0)
    assert not state.powered and state.duty == 0.0
    assert bench.get(Command.GET_ERROR, 0) > 300  # type: ignore[operator]
    # every reply carries the flag, whatever it answers
    assert bench.tx(codec.make_get(Command.GET_VMAX, 2)).stall
    bench.run(0.5)
    assert bench.tx(codec.make_get(Command.GET_VMAX, 2)).stall  # it persists
    assert bench.tx(codec.make_clr()).code == ReplyCode.OK  # cleared before the reply
    assert not bench.tx(codec.make_get(Command.GET_STOP)).stall
    assert bench.get(Command.GET_STOP) == StopStatus()


def test_a_new_start_clears_the_stall(bench: Bench) -> None:
    _stall_axis_0(bench)
    bench.chip.jam(0, jammed=False)
    reply = bench.tx(codec.make_start([0]))
    assert reply.code == ReplyCode.OK
    assert bench.get(Command.GET_STOP) == StopStatus()
    bench.run_until(lambda: not bench.chip.axis_state(0).running, 1.0)
    bench.run(0.05)
    assert abs(bench.encoder(0) - 20_000) <= 2


def test_a_job_write_clears_the_stall(bench: Bench) -> None:
    _stall_axis_0(bench)
    bench.ok(codec.make_set_job(0, Job.TARGET))
    assert bench.get(Command.GET_STOP) == StopStatus()
    assert bench.chip.axis_state(0).powered


def test_an_external_load_beyond_the_motor_stalls_it_at_standstill(bench: Bench) -> None:
    bench.configure(0, limit=100)
    bench.run(0.01)
    bench.chip.motors[0].external_torque_nm = 0.05  # more than the 35 mNm stall torque
    bench.run_until(lambda: bench.chip.axis_state(0).stalled, 0.5)
    assert bench.get(Command.GET_STOP) == StopStatus(frozenset(), frozenset({0}))


# --- gains -------------------------------------------------------------------------------


def test_kabh_overwrites_kabd(bench: Bench) -> None:
    bench.ok(codec.make_set_kab(0, 1, 2, 3, moving=False))
    bench.ok(codec.make_set_kab(0, 40, 50, 60))
    assert bench.get(Command.GET_KABD, 0) == Gains(40, 50, 60)
    bench.ok(codec.make_set_kab(0, 4, 5, 6, moving=False))  # KABD after KABH sticks
    assert bench.get(Command.GET_KABH, 0) == Gains(40, 50, 60)
    assert bench.get(Command.GET_KABD, 0) == Gains(4, 5, 6)


def _hold_deflection(kabd: tuple[int, int, int] | None) -> tuple[float, float]:
    """Max following error of a move, then the deflection under a load at standstill."""
    bench = Bench(Z1100Chip())
    bench.configure(0)
    if kabd is not None:
        bench.ok(codec.make_set_kab(0, *kabd, moving=False))
    bench.ok(codec.make_set_target(0, 10_000))
    bench.ok(codec.make_start([0]))
    errors = bench.watch(0.25, lambda: abs(bench.chip.axis_state(0).error_counts))
    assert not bench.chip.axis_state(0).running
    bench.chip.motors[0].external_torque_nm = 0.004  # 4 mNm pushing the shaft
    bench.run(0.2)
    return max(errors), abs(bench.chip.axis_state(0).error_counts)


def test_kabh_drives_moves_and_kabd_holds_at_standstill() -> None:
    stiff_move, stiff_hold = _hold_deflection(None)  # KABD = KABH
    soft_move, soft_hold = _hold_deflection((2, 16, 8))
    assert soft_move == pytest.approx(stiff_move, abs=2)  # same KABH while moving
    assert stiff_hold <= 10
    assert soft_hold >= 8 * stiff_hold  # the soft standstill gains give way


def _tracking(load_kg_m2: float, gains: tuple[int, int, int]) -> tuple[float, float]:
    """(max following error during a 20000-count move, peak-to-peak error while
    holding 50..150 ms after it) for an axis with this load and these gains."""
    bench = Bench(Z1100Chip.with_loads([load_kg_m2] * 3))
    bench.configure(0, gains, limit=16_000)
    bench.ok(codec.make_set_target(0, 20_000))
    bench.ok(codec.make_start([0]))
    moving = bench.watch(0.3, lambda: abs(bench.chip.axis_state(0).error_counts))
    assert not bench.chip.axis_state(0).running
    bench.run(0.05)
    holding = bench.watch(0.1, lambda: bench.chip.axis_state(0).physical_counts)
    return max(moving), peak_to_peak(holding)


def test_larger_k_tightens_and_much_larger_k_oscillates() -> None:
    soft_error, soft_p2p = _tracking(0.0, (8, 16, 8))
    good_error, good_p2p = _tracking(0.0, (32, 16, 8))
    _, wild_p2p = _tracking(0.0, (255, 16, 8))
    assert good_error < soft_error / 3  # K x 4: about a quarter of the following error
    assert soft_p2p <= 1 and good_p2p <= 1  # both settle
    assert wild_p2p >= 8  # K = 255 never settles: the motor keeps shaking
    assert wild_p2p > 4 * max(good_p2p, 1)


def test_different_loads_need_different_gains() -> None:
    heavy_gains = (128, 64, 8)
    _, light_with_light = _tracking(0.0, GOOD_LIGHT)
    _, light_with_heavy = _tracking(0.0, heavy_gains)
    heavy_error_light, heavy_with_light = _tracking(HEAVY_KG_M2, GOOD_LIGHT)
    heavy_error_heavy, heavy_with_heavy = _tracking(HEAVY_KG_M2, heavy_gains)
    assert light_with_light <= 1 < 6 <= light_with_heavy
    assert heavy_with_heavy <= 1 < 4 <= heavy_with_light
    assert heavy_error_heavy < heavy_error_light


def test_stm_sets_the_sampling_time() -> None:
    for stm in (1, 4):
        chip = Z1100Chip()
        bench = Bench(chip)
        bench.configure(0, job=Job.VELOCITY)
        bench.ok(codec.make_set_stm(0, stm))
        bench.ok(codec.make_start([0], positive=[0]))
        before = chip.samples_run
        bench.run(0.1)
        assert chip.samples_run - before == pytest.approx(0.1 / (stm * 32e-6), rel=0.02)


# --- velocity job, Stop, Estop ----------------------------------------------------------


def test_velocity_job_runs_in_the_commanded_direction_and_stop_decelerates(bench: Bench) -> None:
    bench.configure(0, vmax=50_000, acc=500_000, job=Job.VELOCITY)
    bench.configure(1, vmax=50_000, acc=500_000, job=Job.VELOCITY)
    bench.ok(codec.make_start([0, 1], positive=[0]))
    bench.run(0.3)
    assert bench.get(Command.GET_START) == StartStatus(frozenset({0, 1}), frozenset({0}))
    assert bench.chip.axis_state(0).speed_counts_s == pytest.approx(50_000, rel=0.05)
    assert bench.chip.axis_state(1).speed_counts_s == pytest.approx(-50_000, rel=0.05)
    bench.ok(codec.make_stop([0]))
    before = bench.chip.axis_state(0).encoder_counts  # when the Stop arrived
    assert 0 in bench.running()  # decelerating, not stopped yet
    took_s = bench.run_until(lambda: not bench.chip.axis_state(0).running, 0.5)
    assert took_s == pytest.approx(0.1, abs=0.01)  # 50000 / 500000
    bench.run(0.05)
    # v^2 / 2a = 2500 counts of braking
    assert bench.encoder(0) - before == pytest.approx(2500, abs=150)
    status = bench.get(Command.GET_STOP)
    assert status == StopStatus(frozenset({0}), frozenset())
    assert bench.running() == {1}


def test_stop_does_not_affect_a_move_to_target(bench: Bench) -> None:
    bench.configure(0)
    bench.ok(codec.make_set_target(0, 20_000))
    bench.ok(codec.make_start([0]))
    bench.run(0.05)
    assert bench.ok(codec.make_stop([0])).code == ReplyCode.OK
    bench.run_until(lambda: not bench.chip.axis_state(0).running, 1.0)
    bench.run(0.05)
    assert abs(bench.encoder(0) - 20_000) <= 2
    assert bench.get(Command.GET_STOP) == StopStatus()


def test_estop_stops_at_once(bench: Bench) -> None:
    bench.configure(0, vmax=50_000, acc=500_000, job=Job.VELOCITY)
    bench.ok(codec.make_start([0], positive=[0]))
    bench.run(0.3)
    before = bench.encoder(0)
    bench.ok(codec.make_estop([0]))
    assert bench.running() == frozenset()  # at once
    bench.run(0.05)
    travelled = bench.encoder(0) - before
    assert 0 < travelled < 500  # a Stop would brake over 2500 counts
    assert abs(bench.chip.axis_state(0).speed_counts_s) < 100
    assert bench.get(Command.GET_ESTOP) == StopStatus(frozenset({0}), frozenset())
    assert bench.chip.axis_state(0).powered  # it holds where it stopped


# --- homing ------------------------------------------------------------------------------


@pytest.mark.parametrize("start_counts", [0, -4000])
def test_zero_homes_onto_the_switch(start_counts: int) -> None:
    chip = Z1100Chip([AxisHardware(home_switch_counts=-3000, start_counts=start_counts)] * 3)
    bench = Bench(chip)
    bench.configure(0, busy=True)
    assert bench.get(Command.GET_SWITCH, 0) is (start_counts <= -3000)
    bench.ok(codec.make_zero(0))
    assert bench.running() == {0} and chip.busy_pin == 0
    pressed: list[bool] = []
    while chip.axis_state(0).running:
        bench.run(0.002)
        pressed.append(chip.axis_state(0).switch_pressed)
        assert bench.t < 2.0, "homing did not finish"
    assert True in pressed
    assert chip.busy_pin == 1
    bench.run(0.05)
    # the switch edge is position 0 now; the shaft rests on the edge
    assert abs(bench.encoder(0)) <= 2
    assert abs(chip.axis_state(0).physical_counts - -3000) <= 2
    # moving onto the switch presses it; moving away releases it
    bench.move(0, -500)
    assert bench.get(Command.GET_SWITCH, 0) is True
    bench.move(0, 500)
    assert bench.get(Command.GET_SWITCH, 0) is False


def test_zero_needs_homing_speed_and_acceleration(bench: Bench) -> None:
    bench.configure(0, hac=0)
    bench.ok(codec.make_zero(0))
    assert bench.running() == frozenset()


# --- Cab: wiring mistakes undone in software --------------------------------------------


@pytest.mark.parametrize(
    ("hardware", "fix"),
    [
        (AxisHardware(motor_leads_reversed=True), Cab.MOTOR_REVERSED),
        (AxisHardware(encoder_swapped=True), Cab.ENCODER_SWAPPED),
    ],
)
def test_cab_undoes_reversed_wiring(hardware: AxisHardware, fix: Cab) -> None:
    wrong = Bench(Z1100Chip([hardware] * 3))
    wrong.configure(0, limit=500)
    wrong.ok(codec.make_set_target(0, 5000))
    wrong.ok(codec.make_start([0]))
    wrong.run_until(lambda: wrong.chip.axis_state(0).stalled, 0.5)  # runs away, trips

    fixed = Bench(Z1100Chip([hardware] * 3))
    fixed.ok(codec.make_set_cab(0, fix))
    fixed.configure(0, limit=500)
    fixed.move(0, 5000)
    fixed.run(0.05)
    assert abs(fixed.encoder(0) - 5000) <= 2
    assert fixed.chip.axis_state(0).physical_counts == pytest.approx(5000, abs=2)


def test_cab_bit_2_sets_the_switch_polarity() -> None:
    bench = Bench(Z1100Chip([AxisHardware(switch_active_high=True)] * 3))
    assert bench.get(Command.GET_SWITCH, 0) is True  # not pressed, but the input reads 0
    bench.ok(codec.make_set_cab(0, Cab.SWITCH_ACTIVE_HIGH))
    assert bench.get(Command.GET_SWITCH, 0) is False


# --- flash, resets, baud -----------------------------------------------------------------


def _load_parameters(bench: Bench) -> None:
    for axis in range(3):
        bench.configure(axis, (10 + axis, 20 + axis, 30 + axis), vmax=1000 + axis)
    bench.ok(codec.make_set_stm(1, 9))
    bench.ok(codec.make_set_cab(2, Cab.ENCODER_SWAPPED))


def test_flash_survives_a_power_cycle_in_a_json_file(tmp_path: Path) -> None:
    path = tmp_path / "z1100_flash.json"
    bench = Bench(Z1100Chip(flash_path=path))
    _load_parameters(bench)
    bench.ok(codec.make_flash())
    assert json.loads(path.read_text())["format"] == "servotune-z1100-flash"

    again = Bench(Z1100Chip(flash_path=path))  # a new process, same file
    for axis in range(3):
        assert again.get(Command.GET_KABH, axis) == Gains(10 + axis, 20 + axis, 30 + axis)
        assert again.get(Command.GET_VMAX, axis) == 1000 + axis
        assert again.get(Command.GET_LIMIT, axis) == 2000
        # the job is not saved: motors come up unpowered
        assert again.get(Command.GET_JOB, axis) is Job.FREE
    assert again.get(Command.GET_STM, 1) == 9
    assert again.get(Command.GET_CAB, 2) == Cab.ENCODER_SWAPPED


def test_without_flash_a_power_cycle_loses_everything() -> None:
    bench = Bench(Z1100Chip())
    _load_parameters(bench)
    bench.chip.power_cycle()
    assert bench.get(Command.GET_KABH, 0) == Gains(0, 0, 0)
    assert bench.get(Command.GET_STM, 1) == 1


def test_a_corrupt_flash_file_reads_as_blank(tmp_path: Path) -> None:
    path = tmp_path / "flash.json"
    path.write_text('{"axes": [1, 2')
    bench = Bench(Z1100Chip(flash_path=path))
    assert bench.get(Command.GET_VMAX, 0) == 0


def test_unexpected_reset_is_detectable_by_zero_parameters(bench: Bench) -> None:
    _load_parameters(bench)
    bench.configure(0)
    bench.move(0, 5000)
    assert bench.get(Command.GET_KABH, 0) != Gains(0, 0, 0)
    assert bench.encoder(0) != 0
    bench.chip.inject_reset()
    for axis in range(3):
        # the manual's hint: parameters loaded earlier now read 0
        assert bench.get(Command.GET_KABH, axis) == Gains(0, 0, 0)
        assert bench.get(Command.GET_VMAX, axis) == 0
        assert bench.get(Command.GET_ACC, axis) == 0
        assert bench.get(Command.GET_JOB, axis) is Job.FREE
        assert bench.get(Command.GET_ENCODER, axis) == 0  # the counter restarted
    assert bench.chip.axis_state(0).physical_counts == pytest.approx(5000, abs=2)


def test_a_reset_during_a_move_cuts_the_motor(bench: Bench) -> None:
    bench.configure(0)
    bench.ok(codec.make_set_target(0, 50_000))
    bench.ok(codec.make_start([0]))
    bench.run(0.1)
    bench.chip.inject_reset()
    assert bench.running() == frozenset()
    state = bench.chip.axis_state(0)
    assert not state.powered and state.duty == 0.0
    bench.run(1.0)
    assert bench.chip.axis_state(0).speed_counts_s == 0.0  # friction stopped it


def test_after_a_reset_flashed_parameters_come_back(tmp_path: Path) -> None:
    """So the "reads 0" hint misses resets once parameters are in flash: a host must
    also compare with what it wrote (e.g. Job reads 0 again)."""
    bench = Bench(Z1100Chip(flash_path=tmp_path / "flash.json"))
    _load_parameters(bench)
    bench.ok(codec.make_flash())
    bench.chip.inject_reset()
    assert bench.get(Command.GET_KABH, 0) == Gains(10, 20, 30)
    assert bench.get(Command.GET_JOB, 0) is Job.FREE


def test_baud_changes_after_the_reply_and_resets_to_the_jumpers(bench: Bench) -> None:
    assert bench.chip.baud == 9600
    assert bench.tx(codec.make_set_baud(19200)).code == ReplyCode.OK
    assert bench.chip.baud == 19200
    bench.ok(codec.Request(Command.SET_BAUD, 12345))  # not a jumper rate: ignored
    assert bench.chip.baud == 19200
    bench.chip.power_cycle()
    assert bench.chip.baud == 9600


# --- through a real pseudo-terminal --------------------------------------------------------


def test_through_a_pty_with_pyserial_at_9600_baud() -> None:
    serial = pytest.importorskip("serial")
    from servotune.sim.pty import PtySimulator

    simulator = PtySimulator(Z1100Chip(), baud=9600)
    simulator.start()
    try:
        with serial.Serial(simulator.path, 9600, timeout=1.0) as port:

            def transact(request: codec.Request) -> codec.Reply:
                port.reset_input_buffer()
                port.write(request.encode())
                return codec.decode_reply(port.read(codec.REPLY_SIZE))

            assert transact(codec.make_get(Command.GET_STM, 0)).data == 1
            assert transact(codec.make_set_kab(2, 12, 34, 56)).code == ReplyCode.OK
            reply = transact(codec.make_get_kab(2))
            assert codec.unpack_kab(reply.data) == Gains(12, 34, 56)
            assert transact(codec.Request(0x03)).code == ReplyCode.UNKNOWN_COMMAND
    finally:
        simulator.stop()


def _move_scenario(chip: Z1100Chip) -> list[tuple[object, ...]]:
    """Random moves (gains, speeds, Stm, stall limits, load torques) on every axis; the
    complete state of every axis after each advance."""
    import random
    from dataclasses import replace

    import servotune.devices.z1100.sim.servo as sim

    rng = random.Random(7)
    states: list[tuple[object, ...]] = []
    t_s = 0.0
    for _ in range(25):
        for axis in chip._axes:
            if rng.random() < 0.5:
                k = rng.choice([20, 40, 80, 200])
                axis.p = replace(
                    axis.p,
                    kabh=Gains(k, rng.choice([4, 8, 16]), rng.choice([5, 20, 60])),
                    kabd=Gains(k, 8, 20),
                    vmax_counts_s=rng.choice([5000, 20000, 80000]),
                    acc_counts_s2=rng.choice([50000, 200000, 2000000]),
                    limit_counts=rng.choice([300, 5000, 100000]),
                    stm=rng.choice([1, 1, 2, 5]),
                )
                if not axis.powered:
                    axis.engage()
                axis.mode = sim._MOVE
                axis.running = True
                axis.target_counts = rng.randint(-20000, 20000)
            if rng.random() < 0.2:
                axis.motor.external_torque_nm = rng.uniform(-0.02, 0.02)
                axis.wake()
        for _ in range(12):
            t_s += rng.choice([0.0001, 0.001, 0.005, 0.02])
            chip.advance_to(t_s)
            for axis in chip._axes:
                motor = axis.motor
                fields = {
                    k: v
                    for k, v in vars(axis).items()
                    if not k.startswith("_per_sample") and k not in ("motor", "hardware")
                }
                states.append(
                    (
                        repr(sorted(fields.items())),
                        motor.count,
                        motor.angle_rad,
                        motor.speed_rad_s,
                        motor.current_a,
                        motor.index_crossed,
                    )
                )
    return states


def test_the_move_fast_path_gives_the_same_samples_bit_for_bit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    fast_chip = Z1100Chip()
    fast = _move_scenario(fast_chip)
    import servotune.devices.z1100.sim.servo as sim

    monkeypatch.setattr(sim._Axis, "_move_samples", lambda self, n: 0)
    slow_chip = Z1100Chip()
    slow = _move_scenario(slow_chip)
    assert sum(a.samples for a in fast_chip._axes) == sum(a.samples for a in slow_chip._axes)
    assert sum(a.samples for a in fast_chip._axes) > 50_000  # the moves really ran
    assert fast == slow
