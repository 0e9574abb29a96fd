"""SLAP2 firmware emulation, driven byte by byte in simulation time (no pty).

The ``Wire`` helper plays the manual's host algorithm on an ideal 19200 baud line:
every byte takes one character time to arrive, the device's answer one character
time per byte to come back.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import pytest

from servotune.devices.slap2.sim.controller import FACTORY_DEFAULTS, TICK_S
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.sim.physics import DcMotorParams

CHAR_S = 10 / 19200
CR = b"\r"
CTRL_X = b"\x18"
CTRL_K = b"\x0b"

RSS_LIMIT1 = 1 << 0
RSS_LIMIT2 = 1 << 1
RSS_VM = 1 << 2
RSS_PM = 1 << 3
RSS_MOVE = 1 << 4
RSS_INPOS = 1 << 5
RSS_CAL = 1 << 6
RSS_OC = 1 << 7
RSS_UC = 1 << 8


class Wire:
    def __init__(self, bus: Slap2Line) -> None:
        self.bus = bus
        self.t = 0.0
        self.unsolicited = bus.advance_to(0.0)

    def send(self, data: bytes) -> bytes:
        """Send raw bytes; returns everything the line carried back."""
        out = bytearray()
        for byte in data:
            self.t += CHAR_S
            out += self.bus.advance_to(self.t)
            answer = self.bus.receive(byte)
            self.t += CHAR_S * len(answer)
            out += answer
        return bytes(out)

    def command(self, text: str) -> bytes:
        return self.send(text.encode("ascii") + CR)

    def ask(self, text: str) -> str:
        """Send a command, check the echo, return the reply line(s) without CR."""
        raw = self.command(text)
        echo = text.encode("ascii") + CR
        assert raw.startswith(echo), (text, raw)
        reply = raw[len(echo) :]
        assert reply.endswith(b"\r") or reply.endswith(b"\r\n"), (text, raw)
        return reply.decode("ascii").rstrip("\r\n")

    def number(self, text: str) -> int:
        return int(self.ask(text), 0)

    def run(self, seconds: float) -> bytes:
        self.t += seconds
        return self.bus.advance_to(self.t)

    def tick(self) -> None:
        self.t = (self.bus.ticks + 1) * TICK_S
        self.bus.advance_to(self.t)


def make(*addresses: int, **plant: int | float | None) -> tuple[Slap2Line, Wire]:
    params = DcMotorParams(**plant) if plant else None  # type: ignore[arg-type]
    bus = Slap2Line(Slap2Module(a, params=params) for a in addresses or (0,))
    return bus, Wire(bus)


def wait_until_moved(wire: Wire, timeout_s: float = 10.0) -> None:
    module = wire.bus.modules[0]
    deadline = wire.t + timeout_s
    while (module.moving or module.calibrating) and wire.t < deadline:
        wire.run(0.01)
    assert not module.moving, "the move did not finish"


# --- protocol --------------------------------------------------------------------------


def test_banner_at_power_on_only_from_address_0() -> None:
    bus, wire = make(0, 1)
    assert wire.unsolicited == b"SLAP2 V2205 HW2209 SN10000\r\n"
    assert wire.run(1.0) == b""
    bus.power_cycle(1)
    assert wire.run(0.1) == b""
    bus.power_cycle(None)
    assert wire.run(0.1).count(b"SLAP2") == 1
    bus.power_cycle(0)
    assert wire.run(0.1).startswith(b"SLAP2")


def test_module_other_than_0_powers_up_silent() -> None:
    _, wire = make(3)
    assert wire.unsolicited == b""
    assert wire.command("rp") == b""  # nobody selected: not even an echo
    assert wire.command("se3") == b"\r"  # only the reply of the newly selected module
    assert wire.ask("rp") == "0"


def test_every_byte_is_echoed_before_the_reply() -> None:
    _, wire = make()
    assert wire.send(b"r") == b"r"
    assert wire.send(b"p") == b"p"
    assert wire.send(CR) == b"\r0\r"
    # spaces are echoed and ignored
    assert wire.command("sv 1 2 3") == b"sv 1 2 3\r\r"
    assert wire.ask("rv") == "123"


def test_commands_without_reply_send_a_bare_cr() -> None:
    _, wire = make()
    for command in ("pm", "kp 50", "st", "sipw 7"):
        assert wire.command(command) == command.encode() + b"\r\r"
    assert wire.command("") == b"\r"  # an empty line is no command: just the echo


@pytest.mark.parametrize(
    ("command", "value"),
    [
        ("qp", 40),
        ("qi", 40),
        ("qd", 80),
        ("rv", 2000),
        ("ra", 1000),
        ("rcv", 500),
        ("rca", 200),
        ("ripw", 5),
        ("rw", 5),
        ("ript", 50),
        ("rcl", 2000),
        ("rc", 15),
        ("rsyscon", 3),
        ("ql", 0),
        ("rp", 0),
        ("pe", 0),
        ("rve", 0),
        ("rss", 0),
        ("ss", 64),  # esactiv: both switches enabled by default
    ],
)
def test_factory_defaults_and_numeric_replies(command: str, value: int) -> None:
    _, wire = make()
    assert wire.ask(command) == str(value)


def test_factory_defaults_are_the_manuals() -> None:
    assert FACTORY_DEFAULTS == {
        "kp": 40,
        "ki": 40,
        "kd": 80,
        "sv": 2000,
        "sa": 1000,
        "scv": 500,
        "sca": 200,
        "sipw": 5,
        "sipt": 50,
        "scl": 2000,
        "syscon": 3,
    }


def test_hex_mode_formats_every_number() -> None:
    _, wire = make()
    wire.ask("ssb 4")
    assert wire.ask("rv") == "0x7D0"
    wire.ask("sp -1000")
    assert wire.ask("rp") == "-0x3E8"
    assert wire.ask("rsyscon") == "0x13"
    wire.ask("rsb 4")
    assert wire.ask("rp") == "-1000"


def test_ucon_replies_minus_1uc_to_refused_commands() -> None:
    _, wire = make()
    assert wire.ask("abc") == ""
    wire.ask("ssb 5")
    assert wire.ask("abc") == "-1UC"
    assert wire.ask("kp 40000") == "-1UC"
    assert wire.ask("qp") == "40"
    assert wire.ask("ma 100") == "-1UC"  # no pm
    assert wire.ask("kp 41") == ""


def test_uc_flag_reports_the_previous_command_and_clears() -> None:
    _, wire = make()
    wire.ask("nonsense")
    assert wire.number("rss") & RSS_UC
    assert not wire.number("rss") & RSS_UC  # rss itself was a valid command
    wire.ask("kp 99999")
    assert wire.number("ss") & 1 << 7
    wire.ask("kp 70")
    assert not wire.number("rss") & RSS_UC  # a good command clears it
    wire.ask("xx")
    wire.ask("qp")
    assert not wire.number("rss") & RSS_UC


@pytest.mark.parametrize(
    ("refused", "check", "unchanged"),
    [
        ("kp 40000", "qp", "40"),
        ("ki -1", "qi", "40"),
        ("kd", "qd", "80"),  # missing argument
        ("scl 2001", "rcl", "2000"),
        ("sc 16", "rcl", "2000"),
        ("sv 70000", "rv", "2000"),
        ("sipw 0x10", "ripw", "5"),  # arguments are decimal only
        ("ssyscon 64", "rsyscon", "3"),
        ("ssb 6", "rsyscon", "3"),
        ("spwm 256", "rss", "256"),  # not started (uc of the refused spwm shows)
        ("cal 9", "rss", "256"),
        ("ma 100", "rp", "0"),
        ("rp 5", "rss", "256"),
        ("se 16", "rp", "0"),
        ("il 4", "ql", "0"),
        ("li 2", "rsyscon", "3"),
        ("de 1234", "rss", "256"),  # wrong serial number
    ],
)
def test_refused_commands_set_uc_and_change_nothing(
    refused: str, check: str, unchanged: str
) -> None:
    _, wire = make()
    assert wire.ask(refused) == ""
    assert wire.ask(check) == unchanged
    if check != "rss":
        assert wire.number("rss") & RSS_UC == 0  # the check command was fine


def test_ctrl_x_discards_the_line() -> None:
    _, wire = make()
    wire.ask("pm")
    assert wire.send(b"kp 99" + CTRL_X + CR) == b"kp 99\x18\r"  # echoes only, no reply
    assert wire.ask("qp") == "40"
    assert wire.send(b"ma 5000" + CTRL_X + CR) == b"ma 5000\x18\r"
    wire.run(0.5)
    assert wire.number("rp") == 0
    assert not wire.number("rss") & RSS_MOVE


def test_multidrop_selection() -> None:
    bus, wire = make(0, 1, 2)
    # the echo of "se1" comes from module 0, the reply CR from module 1
    assert wire.command("se1") == b"se1\r\r"
    assert bus.module(1).transmitting and not bus.module(0).transmitting
    wire.ask("kp 77")
    assert bus.module(1).settings["kp"] == 77
    assert bus.module(0).settings["kp"] == 40
    assert bus.module(2).settings["kp"] == 40
    # the selected module switches itself off for an absent address: echo, no reply
    assert wire.command("se5") == b"se5\r"
    assert not any(m.transmitting for m in bus.modules)
    assert wire.command("qp") == b""  # nobody answers, nobody executes
    assert wire.command("kp 5") == b""
    assert all(m.settings["kp"] != 5 for m in bus.modules)
    # a blind "se" still works: non-selected modules parse every line
    assert wire.command("se2") == b"\r"
    assert wire.ask("qp") == "40"
    assert wire.command("se 2") == b"se 2\r\r"  # re-selecting itself: reply CR


def test_id_and_multi_line_listings() -> None:
    _, wire = make()
    assert wire.ask("id") == "SLAP2 SW2205 HW2209 SN10000"
    raw = wire.command("rrss")
    lines = raw[len(b"rrss\r") :].decode().split("\r\n")
    assert lines[-1] == ""  # every line ends CR LF, the last one too
    assert lines[:-1] == [
        "limit1: 0",
        "limit2: 0",
        "vm: 0",
        "pm: 0",
        "move: 0",
        "inpos: 0",
        "cal: 0",
        "oc: 0",
        "uc: 0",
    ]
    syscon = wire.command("rrsyscon").decode()
    assert "l1on: 1\r\n" in syscon and "ucon: 0\r\n" in syscon
    report = wire.command("rep").decode()
    for name, value in FACTORY_DEFAULTS.items():
        assert f"\r\n{name}: {value}\r\n" in report


def test_legacy_commands() -> None:
    _, wire = make()
    wire.ask("ws 9")
    assert wire.ask("ripw") == "9"
    wire.ask("sc 3")
    assert wire.ask("rcl") == "400"
    assert wire.ask("rc") == "3"
    wire.ask("li 0")
    assert wire.ask("rsyscon") == "0"
    assert not wire.number("ss") & 1 << 6  # esactiv
    wire.ask("il 3")
    assert wire.ask("ql") == "3"
    assert wire.number("rss") & (RSS_LIMIT1 | RSS_LIMIT2) == RSS_LIMIT1 | RSS_LIMIT2
    wire.ask("sp 500")
    wire.ask("zp")
    assert wire.ask("rp") == "0"


# --- motion ----------------------------------------------------------------------------


def test_default_gains_settle_a_2000_count_move() -> None:
    bus, wire = make()
    module = bus.module(0)
    wire.ask("pm")
    wire.ask("ma 2000")
    assert wire.number("rss") & RSS_MOVE
    peak = 0
    while module.moving:
        wire.run(0.005)
        peak = max(peak, module.position)
    for _ in range(100):  # 0.3 s after the profile
        wire.run(0.003)
        peak = max(peak, module.position)
    assert peak < 2000 + 30  # hardly any overshoot
    status = wire.number("rss")
    assert status & RSS_INPOS and not status & RSS_MOVE
    assert abs(wire.number("pe")) <= 2
    window = []
    for _ in range(100):  # the motor rests: no sustained oscillation
        wire.run(0.002)
        window.append(module.position)
    assert all(abs(p - 2000) <= 5 for p in window)
    assert max(window) - min(window) <= 2


def test_high_kp_without_damping_oscillates() -> None:
    bus, wire = make()
    module = bus.module(0)
    for command in ("kp 2000", "kd 0", "ki 0", "pm", "ma 2000"):
        wire.ask(command)
    wire.run(1.0)
    positions = []
    for _ in range(200):
        wire.run(0.001)
        positions.append(module.position)
    assert max(positions) - min(positions) > 50
    assert not wire.number("rss") & RSS_INPOS


def test_zero_gains_hold_nothing() -> None:
    bus, wire = make()
    for command in ("kp 0", "ki 0", "kd 0", "pm", "ma 2000"):
        wire.ask(command)
    wait_until_moved(wire)
    assert wire.number("rp") == 0
    assert wire.number("pe") == 2000
    bus.module(0).motor.external_torque_nm = 1e-3  # a push turns the shaft freely
    wire.run(0.1)
    assert wire.number("rp") > 100


def test_inpos_rises_sipt_ticks_after_entering_the_window() -> None:
    bus, wire = make()
    module = bus.module(0)
    wire.ask("sipt 120")
    wire.ask("sipw 2")  # narrow: the motor enters the window after the profile ends
    wire.ask("pm")
    wire.ask("ma 1500")
    ticks: list[tuple[int, bool, bool]] = []  # (position, moving, inpos) after each tick
    while not module.in_position:
        wire.tick()
        ticks.append((module.position, module.moving, module.in_position))
        assert len(ticks) < 5000
    rise = len(ticks) - 1
    entered = 1 + max(k for k, (p, _, _) in enumerate(ticks) if abs(p - 1500) > 2)
    generator_done = min(k for k, (_, moving, _) in enumerate(ticks) if not moving)
    assert entered > generator_done
    assert abs(rise - entered - 120) <= 1
    assert not any(inpos for _, _, inpos in ticks[:-1])


def test_cal_ignores_an_index_pulse_from_before_the_command() -> None:
    bus, wire = make(index_count=300)
    module = bus.module(0)
    wire.ask("pm")
    wire.ask("ma 3000")
    while module.motor.index_crossed is None:  # the move passes the index at 300
        wire.tick()
    for byte in b"cal5\r":  # arrives before the next tick; the cal carries on forwards
        bus.receive(byte)
    wait_until_moved(wire)
    assert module.calibrated
    assert module.setpoint == 300 + 2048  # the next index, not the one just passed


def test_inpos_goes_low_with_every_move() -> None:
    _, wire = make()
    wire.ask("pm")
    wire.run(0.1)
    assert wire.number("rss") & RSS_INPOS  # holding counts as in position
    wire.ask("mr 10")
    assert not wire.number("rss") & RSS_INPOS


def test_new_move_during_a_move_replans_without_a_jump() -> None:
    bus, wire = make()
    module = bus.module(0)
    wire.ask("pm")
    wire.ask("ma 6000")
    wire.run(0.3)
    wire.ask("ma 0")  # reverse mid-way: the generator decelerates first
    setpoints = [module.setpoint]
    for _ in range(40):
        wire.tick()
        setpoints.append(module.setpoint)
    steps = [b - a for a, b in itertools.pairwise(setpoints)]
    max_step = 2000 * 140.417 * 4 / 60 * TICK_S  # sv 2000 in counts per tick
    assert all(abs(step) <= max_step + 1 for step in steps)
    assert steps[0] > 0 and steps[-1] < steps[0]  # still forwards, slowing down
    wait_until_moved(wire)
    wire.run(0.3)
    assert abs(wire.number("rp")) <= 5


def test_set_position_while_moving_does_not_disturb_the_move() -> None:
    bus, wire = make()
    module = bus.module(0)
    wire.ask("pm")
    wire.ask("ma 4000")
    wire.run(0.3)
    at_sp = module.position
    wire.ask("sp 0")
    assert abs(wire.number("pe")) < 50  # no jump of the following error
    wait_until_moved(wire)
    wire.run(0.3)
    # the shaft ends where the move was going; only the numbering changed
    assert module.motor.count == pytest.approx(4000, abs=5)
    assert at_sp <= 4000 - wire.number("rp") <= at_sp + 100


def test_short_moves_become_triangles_and_deccel_is_reported() -> None:
    bus, wire = make()
    wire.ask("pm")
    wire.ask("mr 200")
    saw_deccel = False
    while bus.module(0).moving:
        wire.run(0.005)
        saw_deccel = saw_deccel or bool(wire.number("ss") & 1 << 5)
    assert saw_deccel
    wire.run(0.3)
    assert wire.number("rp") == pytest.approx(200, abs=5)


def test_velocity_mode_follows_sv_and_refuses_a_negative_one() -> None:
    _, wire = make(limit1_count=None, limit2_count=None)
    wire.ask("sv 1000")
    wire.ask("vm")
    wire.run(0.6)
    assert wire.number("rve") == pytest.approx(1000, rel=0.05)
    assert wire.number("rss") & (RSS_VM | RSS_MOVE | RSS_PM) == RSS_VM
    wire.ask("sv 500")  # changes apply while running
    wire.run(0.6)
    assert wire.number("rve") == pytest.approx(500, rel=0.05)
    # sv is a speed (manual): a sign is refused and changes nothing.
    wire.ask("sv -500")
    assert wire.number("rss") & RSS_UC
    assert wire.number("rv") == 500
    wire.run(0.3)
    assert wire.number("rve") == pytest.approx(500, rel=0.05)


def test_stop_unpowers_the_motor_but_the_counter_keeps_counting() -> None:
    _, wire = make(limit1_count=None, limit2_count=None)
    wire.ask("sv 3000")
    wire.ask("vm")
    wire.run(0.5)
    wire.ask("st")
    assert wire.number("rss") & (RSS_VM | RSS_PM) == 0
    first = wire.number("rp")
    wire.run(0.01)
    assert wire.number("rp") > first  # coasting
    wire.run(1.0)
    resting = wire.number("rp")
    wire.run(0.5)
    assert wire.number("rp") == resting  # friction stopped it, nothing drives it


def test_open_loop_pwm() -> None:
    _, wire = make(limit1_count=None, limit2_count=None)
    wire.ask("spwm -100")
    wire.run(0.3)
    assert wire.number("rve") < -5000
    assert wire.number("rss") & (RSS_VM | RSS_PM) == 0
    assert wire.ask("pg") == ""  # allowed outside pm/vm
    assert not wire.number("rss") & RSS_UC


def test_limit_switch_stops_a_move_and_blocks_further_moves_into_it() -> None:
    bus, wire = make(limit2_count=3000)
    module = bus.module(0)
    wire.ask("sv 5000")
    wire.ask("pm")
    wire.ask("ma 10000")
    wait_until_moved(wire, 3.0)
    wire.run(0.2)
    status = wire.number("rss")
    assert status & RSS_LIMIT2 and status & RSS_PM and not status & RSS_MOVE
    stopped_at = wire.number("rp")
    assert 3000 <= stopped_at < 3300
    wire.ask("mr 100")  # further into the switch: stopped again at once
    wire.tick()
    wire.tick()
    assert not module.moving
    wire.run(0.2)
    assert abs(wire.number("rp") - stopped_at) <= 5
    wire.ask("ma 0")  # away from the switch is allowed
    wait_until_moved(wire, 3.0)
    wire.run(0.3)
    assert abs(wire.number("rp")) <= 5
    assert not wire.number("rss") & RSS_LIMIT2


def test_disabled_limit_switch_does_not_stop() -> None:
    _, wire = make(limit2_count=3000)
    wire.ask("rsb 1")  # l2on off
    wire.ask("pm")
    wire.ask("ma 5000")
    wait_until_moved(wire, 5.0)
    wire.run(0.3)
    assert wire.number("rp") == pytest.approx(5000, abs=5)
    assert wire.number("rss") & RSS_LIMIT2  # the level is still reported


def test_current_limit_sets_oc_only_when_reached() -> None:
    bus, wire = make(limit2_count=None)
    module = bus.module(0)
    for command in ("sv 20000", "sa 20000", "pm", "ma 10000"):
        wire.ask(command)
    limited_default = 0
    while module.moving:
        wire.tick()
        limited_default += module.current_limited
    assert limited_default == 0
    wire.ask("scl 50")
    wire.ask("ma 0")
    limited_ticks = 0
    saw_oc_on_wire = False
    while module.moving:
        wire.run(0.002)
        limited_ticks += module.current_limited
        saw_oc_on_wire = saw_oc_on_wire or bool(wire.number("rss") & RSS_OC)
    assert limited_ticks > 10
    assert saw_oc_on_wire
    assert abs(module.motor.current_a) <= 0.050 + 1e-9


# --- calibration -----------------------------------------------------------------------

E1, E2, INDEX = -3000, 3000, 300


def calibrate(mode: int, *, start: int = 0) -> tuple[Slap2Line, Wire]:
    bus, wire = make(limit1_count=E1, limit2_count=E2, index_count=INDEX)
    bus.module(0).motor.set_count(start)
    wire.ask("sp 0")
    wire.ask(f"cal {mode}")
    status = wire.number("rss")
    assert status & RSS_MOVE and not status & RSS_CAL
    wait_until_moved(wire, 20.0)
    wire.run(0.5)
    return bus, wire


@pytest.mark.parametrize("mode", [0, 1])
def test_cal_on_a_switch_ends_at_its_edge(mode: int) -> None:
    bus, wire = calibrate(mode)
    status = wire.number("rss")
    assert status & RSS_CAL and status & RSS_PM and not status & RSS_MOVE
    assert status & RSS_INPOS
    count = bus.module(0).motor.count  # physical count; the counter started at 0
    if mode == 0:
        assert E1 < count + 1 <= E1 + 3  # just released E1
    else:
        assert E2 - 3 <= count - 1 < E2


@pytest.mark.parametrize(("mode", "index"), [(2, INDEX - 2048), (3, INDEX + 2048)])
def test_cal_on_switch_and_index_ends_at_the_first_index_after_the_switch(
    mode: int, index: int
) -> None:
    _, wire = calibrate(mode)
    assert wire.number("rss") & RSS_CAL
    setpoint = wire.number("rp") + wire.number("pe")
    assert setpoint == index
    assert abs(wire.number("pe")) <= 2


@pytest.mark.parametrize(("mode", "index"), [(4, INDEX - 2048), (5, INDEX)])
def test_cal_on_index_only(mode: int, index: int) -> None:
    _, wire = calibrate(mode)
    assert wire.number("rss") & RSS_CAL
    assert wire.number("rp") + wire.number("pe") == index


def test_cal_standing_in_the_switch_drives_out_of_it() -> None:
    bus, wire = calibrate(0, start=E1 - 200)
    assert wire.number("rss") & RSS_CAL
    assert E1 < bus.module(0).motor.count + 1 <= E1 + 3


def test_ca_uses_sv_and_sa() -> None:
    bus, wire = make(limit1_count=E1)
    module = bus.module(0)
    wire.ask("sv 4000")
    wire.ask("ca 0")
    wire.run(0.5)
    fast = module.motor.speed_rad_s
    wire.ask("st")
    wire.run(1.0)
    wire.ask("sp 0")
    wire.ask("cal 0")  # scv 500 by default
    wire.run(0.5)
    assert abs(fast) > 4 * abs(module.motor.speed_rad_s)


def test_ctrl_k_aborts_calibration_and_cal_stays_0() -> None:
    bus, wire = make(limit1_count=E1)
    wire.ask("cal 0")
    wire.run(0.2)
    assert wire.send(CTRL_K) == CTRL_K
    status = wire.number("rss")
    assert not status & RSS_MOVE and not status & RSS_CAL and status & RSS_PM
    wire.run(0.3)
    resting = wire.number("rp")
    wire.run(3.0)
    assert abs(wire.number("rp") - resting) <= 2
    assert not wire.number("rss") & RSS_CAL
    assert bus.module(0).motor.count > E1


# --- EEPROM and power ------------------------------------------------------------------


def test_pg_persists_and_de_erases(tmp_path: Path) -> None:
    path = tmp_path / "slap2_0.json"
    bus = Slap2Line([Slap2Module(0, eeprom_path=path, serial_number=4711)])
    wire = Wire(bus)
    wire.ask("kp 55")
    wire.ask("sv 3000")
    wire.ask("ssyscon 1")
    assert wire.ask("pg") == ""
    assert json.loads(path.read_text())["settings"]["kp"] == 55
    wire.ask("kp 66")  # not stored
    bus.power_cycle()
    wire.run(0.1)
    assert wire.ask("qp") == "55"
    assert wire.ask("rv") == "3000"
    assert wire.ask("rsyscon") == "1"
    assert wire.ask("de 4712") == ""
    assert wire.number("rss") & RSS_UC
    assert wire.ask("de 4711") == ""
    assert wire.ask("qp") == "55"  # RAM unchanged until the next power-on
    bus.power_cycle()
    wire.run(0.1)
    assert wire.ask("qp") == "40"
    assert wire.ask("rv") == "2000"


def test_pg_is_refused_in_pm_and_vm() -> None:
    bus = Slap2Line([Slap2Module(0)])
    wire = Wire(bus)
    wire.ask("ssb 5")
    wire.ask("kp 55")
    wire.ask("pm")
    assert wire.ask("pg") == "-1UC"
    wire.ask("vm")
    assert wire.ask("pg") == "-1UC"
    wire.ask("st")
    assert wire.ask("pg") == ""
    bus.power_cycle()
    wire.run(0.1)
    assert wire.ask("qp") == "55"


def test_power_cycle_resets_ram_counter_modes_and_cal_flag() -> None:
    bus, wire = calibrate(5)
    wire.ask("kp 99")
    wire.ask("ma 1000")
    wait_until_moved(wire)
    wire.run(0.2)
    bus.power_cycle()
    assert wire.run(0.01).startswith(b"SLAP2")
    assert wire.number("rp") == 0
    assert wire.number("rss") & (RSS_CAL | RSS_PM | RSS_MOVE) == 0
    assert wire.ask("qp") == "40"


def test_corrupt_eeprom_file_means_defaults(tmp_path: Path) -> None:
    path = tmp_path / "slap2_0.json"
    path.write_text("{not json")
    wire = Wire(Slap2Line([Slap2Module(0, eeprom_path=path)]))
    assert wire.ask("qp") == "40"


def test_time_never_runs_backwards_and_ticks_are_exact() -> None:
    bus, _ = make()
    bus.advance_to(1.0)
    ticks = bus.ticks
    assert ticks == int(1.0 / TICK_S)
    bus.advance_to(0.5)
    assert bus.ticks == ticks
    bus.advance_to(1.0 + TICK_S)
    assert bus.ticks == ticks + 1


def test_same_inputs_same_outputs() -> None:
    def session() -> bytes:
        _, wire = make()
        out = bytearray()
        for command in ("pm", "ma 3000", "rp", "pe", "rve", "rss"):
            out += wire.command(command)
            wire.run(0.037)
        return bytes(out)

    assert session() == session()


def test_the_idle_fast_path_gives_the_same_state_bit_for_bit() -> None:
    """``run_ticks`` (ticks at a fixed point skipped) against ``tick`` one by one."""
    import random

    def send(module: Slap2Module, line: str) -> bytes:
        return b"".join(module.receive(byte) for byte in (line + "\r").encode())

    def state(module: Slap2Module) -> tuple[object, ...]:
        fields = {
            k: repr(v)
            for k, v in (vars(module) | vars(module.controller)).items()
            if k not in ("_commands", "controller", "motor", "_frozen", "_last_fingerprint")
        }
        motor = module.motor
        return (sorted(fields.items()), motor.count, motor.angle_rad, motor.speed_rad_s)

    fast, slow = Slap2Module(0), Slap2Module(0)
    rng = random.Random(1)
    lines = ["pm", "ma2000", "mr-500", "sv3000", "ma0", "vm", "sv1000", "st", "pm", "ma100"]
    skipped = 0
    for line in [*lines, "spwm40", "st", "pm", "ma-3000"]:
        assert send(fast, line) == send(slow, line)
        for _ in range(30):
            n = rng.choice([1, 3, 50, 400, 1200])
            fast.run_ticks(n)
            for _ in range(n):
                slow.tick()
            skipped += fast.controller._frozen is not None
            assert state(fast) == state(slow), line
        if rng.random() < 0.5:
            torque = rng.uniform(-0.01, 0.01)
            fast.motor.external_torque_nm = slow.motor.external_torque_nm = torque
    assert skipped > 0  # the fast path was taken
