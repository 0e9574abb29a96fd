"""The SLAP2 device descriptor: parameters, channels, flags and commands as data.

Texts paraphrase the vendor manual (``shared/seeds/000_...``, German) in English.
Unit conversions use the manual's formulas and the encoder line count of the link
(``lines`` in the link spec): rpm = SV * 140.417 / lines, rpm/min = SA * 35946.7 /
lines, ms = ticks * 0.8415.
"""

from __future__ import annotations

from servotune.descriptor import (
    ArgumentDescriptor,
    BitDescriptor,
    ChannelDescriptor,
    Choice,
    CommandDescriptor,
    ConsoleDescriptor,
    ConsoleRule,
    Conversion,
    DeviceDescriptor,
    FlagDescriptor,
    JogDescriptor,
    JogPress,
    LoopSignals,
    MoveTarget,
    ParameterDescriptor,
    PlotDescriptor,
    StopEffect,
    TwinDescriptor,
)
from servotune.devices.slap2 import NAME, codec

POSITION_LIMIT = codec.POSITION_LIMIT

# Console mnemonics that set a descriptor parameter (the driver forgets what it knew of
# that parameter after such a line; the permission table checks the line as a write).
PARAM_SETTERS = {
    "kp": "kp",
    "ki": "ki",
    "kd": "kd",
    "sv": "velocity",
    "sa": "acceleration",
    "sipw": "inpos_window",
    "ws": "inpos_window",
    "sipt": "inpos_time",
    "scl": "current_limit_ma",
    "sc": "current_limit_ma",
    "scv": "cal_velocity",
    "sca": "cal_acceleration",
    "ssyscon": "syscon",
    "ssb": "syscon",
    "rsb": "syscon",
    "li": "syscon",
    "il": "syscon",
}
# Console mnemonics that only read (``se`` is refused by the driver: servotune selects).
READ_MNEMONICS = (
    "rp", "pe", "rve", "rss", "ss", "rrss", "rv", "ra", "rcv", "rca", "qp", "qi", "qd",
    "ripw", "rw", "ript", "rcl", "rc", "rsyscon", "rrsyscon", "ql", "id", "rep",
)  # fmt: skip
# Console mnemonics that are a descriptor command.
COMMAND_MNEMONICS = {
    "st": "stop",
    "pm": "position_mode",
    "vm": "velocity_mode",
    "ma": "move_absolute",
    "mr": "move_relative",
    "sp": "set_position",
    "zp": "set_position",
    "spwm": "open_loop_pwm",
    "cal": "calibrate",
    "ca": "calibrate",
    "pg": "save_eeprom",
}


def console_rules() -> list[ConsoleRule]:
    """What every SLAP2 console mnemonic does. The module ignores spaces and (as its
    manual's own examples in capitals show) case: ``PG``, `` pg`` and ``p g`` are
    ``pg``; the console's ``letters`` syntax reads a line the same way."""
    rules = [ConsoleRule(words=list(READ_MNEMONICS), effect="read")]
    for parameter in sorted(set(PARAM_SETTERS.values())):
        words = [m for m, p in PARAM_SETTERS.items() if p == parameter]
        rules.append(ConsoleRule(words=words, effect="write", parameters=[parameter]))
    for command in dict.fromkeys(COMMAND_MNEMONICS.values()):
        words = [m for m, c in COMMAND_MNEMONICS.items() if c == command]
        rules.append(ConsoleRule(words=words, effect="command", command=command))
    # de: erase the EEPROM (defaults at the next power-on): as persisting as pg.
    rules.append(ConsoleRule(words=["de"], effect="persist"))
    return rules


CALIBRATION_MODES = [
    Choice(
        value=0,
        label="cal 0: limit switch E1",
        description=(
            "Drive toward E1 (negative) with scv/sca; stop at once on E1; back off toward "
            "E2 at 1/16 speed and acceleration until E1 releases; stop."
        ),
    ),
    Choice(
        value=1,
        label="cal 1: limit switch E2",
        description=(
            "Drive toward E2 (positive) with scv/sca; stop at once on E2; back off toward "
            "E1 at 1/16 speed and acceleration until E2 releases; stop."
        ),
    ),
    Choice(
        value=2,
        label="cal 2: E1 + index",
        description="As cal 0, then keep turning (toward E2) until the encoder's index pulse.",
    ),
    Choice(
        value=3,
        label="cal 3: E2 + index",
        description="As cal 1, then keep turning (toward E1) until the encoder's index pulse.",
    ),
    Choice(
        value=4,
        label="cal 4: index, negative",
        description="Turn in the negative direction until the index pulse only; stop.",
    ),
    Choice(
        value=5,
        label="cal 5: index, positive",
        description="Turn in the positive direction until the index pulse only; stop.",
    ),
]

SYSCON_BITS = [
    BitDescriptor(bit=0, name="l1on", label="E1 on", description="Limit switch E1 enabled."),
    BitDescriptor(bit=1, name="l2on", label="E2 on", description="Limit switch E2 enabled."),
    BitDescriptor(
        bit=2, name="inv1", label="invert E1", description="E1 level inverted (normally open)."
    ),
    BitDescriptor(
        bit=3, name="inv2", label="invert E2", description="E2 level inverted (normally open)."
    ),
    BitDescriptor(
        bit=4,
        name="hex",
        label="hex output",
        description="The module answers numbers in hex (0x3E8). servotune reads both forms.",
    ),
    BitDescriptor(
        bit=5,
        name="ucon",
        label="-1UC replies",
        description="Unknown or refused commands answer '-1UC' instead of an empty line.",
    ),
]


def slap2_descriptor(lines: int) -> DeviceDescriptor:
    """Build the descriptor for a SLAP2 axis whose encoder has ``lines`` lines per rev."""
    counts_per_rev = 4 * lines
    rpm_per_sv = codec.RPM_PER_SV_LINE / lines
    rpm_min_per_sa = codec.RPM_PER_MIN_PER_SA_LINE / lines
    counts_s_per_sv = codec.COUNTS_S_PER_SV
    revs = Conversion(unit="rev", factor=1 / counts_per_rev, digits=3)
    deg = Conversion(unit="°", factor=360 / counts_per_rev, digits=1)
    rpm_of_counts_s = Conversion(unit="rpm", factor=60 / counts_per_rev, digits=1)
    parameters = [
        ParameterDescriptor(
            name="kp",
            label="P gain",
            unit="",
            minimum=0,
            maximum=codec.GAIN_MAX,
            default=40,
            persisted=True,
            group="gains",
            description="Proportional gain: stiffness. Raise with D; too much oscillates.",
            set_command="kp{value}",
            read_command="qp",
            slider_maximum=2000,
        ),
        ParameterDescriptor(
            name="ki",
            label="I gain",
            unit="",
            minimum=0,
            maximum=codec.GAIN_MAX,
            default=40,
            persisted=True,
            group="gains",
            description=(
                "Integral gain: accuracy at the target. The manual: tune with I at 0 or 1 "
                "first, then raise I until positioning is accurate."
            ),
            set_command="ki{value}",
            read_command="qi",
            slider_maximum=2000,
        ),
        ParameterDescriptor(
            name="kd",
            label="D gain",
            unit="",
            minimum=0,
            maximum=codec.GAIN_MAX,
            default=80,
            persisted=True,
            group="gains",
            description="Derivative gain: damps oscillation. Vary D against ringing.",
            set_command="kd{value}",
            read_command="qd",
            slider_maximum=4000,
        ),
        ParameterDescriptor(
            name="velocity",
            label="Velocity (sv)",
            unit="sv",
            # The manual defines sv as a speed ("maximale Verfahrgeschwindigkeit/
            # Motordrehzahl", an rpm by its formula) and never gives it a sign; its own
            # way to drive the other way is pm + ma to a negative position. A negative
            # sv is refused here (field error), nothing sent; Jog ◀ reverses.
            minimum=0,
            maximum=codec.VELOCITY_MAX,
            default=2000,
            persisted=True,
            group="profile",
            description=(
                "Profile velocity of moves, and the speed of velocity mode (may change "
                "while running). A speed, never negative (the manual gives it no sign): "
                "to turn the other way, move or jog to lower positions. "
                f"rpm = SV x {codec.RPM_PER_SV_LINE} / lines."
            ),
            set_command="sv{value}",
            read_command="rv",
            conversions=[
                Conversion(unit="rpm", factor=rpm_per_sv, digits=1),
                Conversion(unit="counts/s", factor=counts_s_per_sv, digits=0),
            ],
            slider_maximum=20000,
        ),
        ParameterDescriptor(
            name="acceleration",
            label="Acceleration (sa)",
            unit="sa",
            minimum=0,
            maximum=codec.ACCELERATION_MAX,
            default=1000,
            persisted=True,
            group="profile",
            description=(
                "Acceleration and deceleration of moves and of velocity mode. "
                f"rpm/min = SA x {codec.RPM_PER_MIN_PER_SA_LINE} / lines."
            ),
            set_command="sa{value}",
            read_command="ra",
            conversions=[
                Conversion(unit="rpm/min", factor=rpm_min_per_sa, digits=0),
                Conversion(unit="counts/s²", factor=codec.COUNTS_S2_PER_SA, digits=0),
            ],
            slider_maximum=10000,
        ),
        ParameterDescriptor(
            name="inpos_window",
            label="In-position window (sipw)",
            unit="counts",
            minimum=0,
            maximum=codec.WINDOW_MAX,
            default=5,
            persisted=True,
            group="in-position",
            description=(
                "inpos needs the motor within ± this many counts of the target for the "
                "in-position time."
            ),
            set_command="sipw{value}",
            read_command="ripw",
            slider_maximum=200,
        ),
        ParameterDescriptor(
            name="inpos_time",
            label="In-position time (sipt)",
            unit="ticks",
            minimum=0,
            maximum=codec.WINDOW_MAX,
            default=50,
            persisted=True,
            group="in-position",
            description=(
                f"Ticks of {codec.TICK_S * 1e6:.1f} µs the motor must stay inside the window "
                "before inpos "
                "goes high (50 ≈ 42 ms)."
            ),
            set_command="sipt{value}",
            read_command="ript",
            conversions=[Conversion(unit="ms", factor=codec.TICK_S * 1000, digits=1)],
            slider_maximum=1000,
        ),
        ParameterDescriptor(
            name="current_limit_ma",
            label="Current limit (scl)",
            unit="mA",
            minimum=0,
            maximum=codec.CURRENT_LIMIT_MAX_MA,
            default=2000,
            persisted=True,
            group="limits",
            description=(
                "Motor current limit. While it acts, the oc flag is high: usually a sign "
                "that something in motor or mechanics is wrong."
            ),
            set_command="scl{value}",
            read_command="rcl",
        ),
        ParameterDescriptor(
            name="cal_velocity",
            label="Calibration velocity (scv)",
            unit="sv",
            minimum=0,
            maximum=codec.VELOCITY_MAX,
            default=500,
            persisted=True,
            group="calibration",
            description="Velocity of cal 0..5 (ca uses sv). Same units as sv.",
            set_command="scv{value}",
            read_command="rcv",
            conversions=[Conversion(unit="rpm", factor=rpm_per_sv, digits=1)],
            slider_maximum=5000,
        ),
        ParameterDescriptor(
            name="cal_acceleration",
            label="Calibration acceleration (sca)",
            unit="sa",
            minimum=0,
            maximum=codec.ACCELERATION_MAX,
            default=200,
            persisted=True,
            group="calibration",
            description="Acceleration of cal 0..5. A switch stops the motor abruptly anyway.",
            set_command="sca{value}",
            read_command="rca",
            conversions=[Conversion(unit="rpm/min", factor=rpm_min_per_sa, digits=0)],
            slider_maximum=5000,
        ),
        ParameterDescriptor(
            name="syscon",
            label="System configuration (ssyscon)",
            unit="",
            minimum=0,
            maximum=63,
            default=3,
            persisted=True,
            group="configuration",
            description=(
                "Limit switches on/off and their polarity, hex output, -1UC replies. "
                "Rotary axes without switches must clear E1 on / E2 on."
            ),
            set_command="ssyscon{value}",
            read_command="rsyscon",
            kind="bits",
            bits=SYSCON_BITS,
            slider=False,
        ),
    ]
    channels = [
        ChannelDescriptor(
            name="position",
            label="Position",
            unit="counts",
            description="Encoder position (rp). The counter runs in every mode.",
            conversions=[revs, deg],
        ),
        ChannelDescriptor(
            name="setpoint",
            label="Setpoint",
            unit="counts",
            description=(
                "Profile generator setpoint: the move servotune commanded, replayed through "
                "the firmware's trapezoid law and checked against pe; where there is none, "
                "position + pe while pe is steady. Empty otherwise: rp and pe are read a "
                "transaction apart, and on a ringing axis their sum is no setpoint."
            ),
            conversions=[revs, deg],
        ),
        ChannelDescriptor(
            name="following_error",
            label="Following error",
            unit="counts",
            description="pe: setpoint minus actual position (Schleppfehler).",
            conversions=[deg],
        ),
        ChannelDescriptor(
            name="velocity",
            label="Velocity",
            unit="counts/s",
            description="Derived from successive positions and their times.",
            conversions=[rpm_of_counts_s],
        ),
        ChannelDescriptor(
            name="velocity_measured",
            label="Velocity (rve)",
            unit="counts/s",
            description="The module's own velocity measurement, read at a lower rate.",
            conversions=[rpm_of_counts_s],
        ),
    ]
    flag_texts = {
        "limit1": ("E1", "Level at limit switch input E1 (negative end).", "warning"),
        "limit2": ("E2", "Level at limit switch input E2 (positive end).", "warning"),
        "vm": ("vm", "Velocity mode is on. Low after st.", "info"),
        "pm": ("pm", "Position mode is on. Low after st.", "info"),
        "move": (
            "move",
            "The profile generator is running (after ma/mr); the next move may start "
            "when it is low. The setpoint need not equal the position yet (see pe).",
            "info",
        ),
        "inpos": (
            "inpos",
            "Motor in position: within ±sipw of the target for sipt ticks "
            f"({codec.TICK_S * 1e6:.1f} µs "
            "each). Goes low at the start of every move.",
            "info",
        ),
        "cal": ("cal", "Calibrated with cal/ca since power-on.", "info"),
        "oc": (
            "oc",
            "Current limit active: the motor wants more current than scl allows. "
            "Normally a sign that motor or mechanics are not in order.",
            "fault",
        ),
        "uc": (
            "uc",
            "The previous command was unknown, malformed or could not be executed.",
            "warning",
        ),
    }
    flags = [
        FlagDescriptor(
            name=bit.name,
            label=flag_texts[bit.name][0],
            description=flag_texts[bit.name][1],
            bit=bit.value,
            source="rss",
            severity=flag_texts[bit.name][2],  # type: ignore[arg-type]
        )
        for bit in codec.RssBit
    ]
    plots = [
        PlotDescriptor(
            name="position", label="Position", unit="counts", series=["position", "setpoint"]
        ),
        PlotDescriptor(
            name="following_error",
            label="Following error",
            unit="counts",
            series=["following_error"],
        ),
        PlotDescriptor(
            name="velocity",
            label="Velocity",
            unit="counts/s",
            series=["velocity", "velocity_measured"],
        ),
        PlotDescriptor(
            name="flags",
            label="Flags",
            unit="",
            series=["move", "inpos", "oc", "limit1", "limit2"],
            kind="flags",
        ),
    ]
    position_arg = ArgumentDescriptor(
        name="position",
        label="Position",
        unit="counts",
        minimum=-POSITION_LIMIT,
        maximum=POSITION_LIMIT,
        required=True,
    )
    commands = [
        CommandDescriptor(
            name="stop",
            label="STOP",
            description=(
                "Shortest stop, then holds: in velocity mode pm, in position mode st + pm "
                "- the loop holds the position where the shaft is, braking with the full "
                "supply. Open-loop PWM or a coasting shaft: spwm 0 (winding shorted), st "
                "once at rest. An unpowered motor is never powered: st only. A loop that "
                "is not working (oscillating, error growing, current limit held) is not "
                "trusted to hold: spwm 0, then st."
            ),
            group="stop",
        ),
        CommandDescriptor(
            name="power_off",
            label="Power off (st)",
            description=(
                "st: controller off, motor unpowered at once (stop category 0); leaves "
                "pm, vm and spwm. The shaft coasts: a vertical or loaded axis drops."
            ),
            group="stop",
        ),
        CommandDescriptor(
            name="jog_stop",
            label="Decelerate and hold",
            description=(
                "Ends a jog or a move: ma to where the running profile stops with sa, "
                "then holds there (no return). Without a known profile: as STOP."
            ),
            group="stop",
        ),
        CommandDescriptor(
            name="hold",
            label="Stop and hold",
            description=(
                "Keep the motor powered and hold the position: without pm (after st, in "
                "vm or spwm) it sends pm, which turns the controller on at the current "
                "position (a firm stop, no ramp); in pm with a move running it sends ma "
                "to the position at the press, so the profile brakes with sa and returns "
                "there. Refused by the module while a calibration runs (use Abort "
                "calibration or STOP)."
            ),
            group="stop",
            powers_motor=True,
        ),
        CommandDescriptor(
            name="position_mode",
            label="Position mode",
            description="pm: controller on, holds the current position.",
            group="mode",
            active_flag="pm",
        ),
        CommandDescriptor(
            name="velocity_mode",
            label="Velocity mode",
            description="vm: controller on, accelerates with sa to sv at once.",
            group="mode",
            active_flag="vm",
        ),
        CommandDescriptor(
            name="jog",
            label="Jog",
            description=(
                "Hold to run: pm (unless on), then ma towards the end of the range in the "
                "direction, at sv and sa; the release decelerates with sa and holds."
            ),
            group="motion",
            hold_to_run=True,
            arguments=[
                ArgumentDescriptor(
                    name="direction",
                    label="Direction",
                    minimum=-1,
                    maximum=1,
                    default=1,
                    required=True,
                    choices=[
                        Choice(value=1, label="+", description="towards positive counts (E2)"),
                        Choice(value=-1, label="−", description="towards negative counts (E1)"),
                    ],
                )
            ],
        ),
        CommandDescriptor(
            name="move_absolute",
            label="Move to",
            description="ma: move to a position (needs position mode).",
            group="motion",
            arguments=[position_arg],
            target=MoveTarget(argument="position"),
        ),
        CommandDescriptor(
            name="move_relative",
            label="Move by",
            description="mr: move by a distance (needs position mode). Jog uses it too.",
            group="motion",
            arguments=[
                ArgumentDescriptor(
                    name="distance",
                    label="Distance",
                    unit="counts",
                    minimum=-2 * POSITION_LIMIT,
                    maximum=2 * POSITION_LIMIT,
                    default=2000,
                    required=True,
                )
            ],
            target=MoveTarget(argument="distance", relative=True),
        ),
        CommandDescriptor(
            name="set_position",
            label="Set position",
            description="sp: set the position counter (allowed while moving).",
            group="motion",
            arguments=[position_arg],
        ),
        CommandDescriptor(
            name="open_loop_pwm",
            label="Open-loop PWM",
            description=(
                "spwm: drive the motor with a fixed PWM, no position control and no "
                "encoder needed. -255..255 (the manual's table says ±254; its command "
                "section ±255)."
            ),
            group="motion",
            arguments=[
                ArgumentDescriptor(
                    name="pwm",
                    label="PWM",
                    unit="",
                    minimum=-255,
                    maximum=255,
                    default=30,
                    required=True,
                )
            ],
            confirm=(
                "Open-loop PWM turns the motor without position control. Limit switches "
                "do not hold it. Make sure the mechanics can turn freely."
            ),
        ),
        CommandDescriptor(
            name="calibrate",
            label="Calibrate",
            description="cal n: home on a limit switch and/or the index pulse with scv/sca.",
            group="calibration",
            arguments=[
                ArgumentDescriptor(
                    name="mode",
                    label="Mode",
                    minimum=0,
                    maximum=5,
                    default=4,
                    required=True,
                    choices=CALIBRATION_MODES,
                )
            ],
            abort_command="abort_calibration",
        ),
        CommandDescriptor(
            name="abort_calibration",
            label="Abort calibration",
            description="Ctrl-K: aborts a running calibration; the cal flag stays 0.",
            group="calibration",
        ),
        CommandDescriptor(
            name="save_eeprom",
            label="Save to EEPROM",
            description=(
                "pg: store kp ki kd sipw sipt scv sca scl syscon sv sa in the module's "
                "EEPROM (restored at power-on). Not while pm or vm is on: stop first."
            ),
            group="persist",
            confirm="Store the current settings permanently in the module's EEPROM?",
            stores_parameters="axis",
        ),
        CommandDescriptor(
            name="restore_parameters",
            label="Re-apply last settings",
            description=(
                "Write the last settings servotune applied or read to this module again "
                "(after a reset)."
            ),
            group="persist",
        ),
    ]
    return DeviceDescriptor(
        device=NAME,
        model="gräbner SLAP2",
        title="SLAP2 DC servo module",
        summary=(
            f"Brushed DC motor, PID position loop, quadrature encoder ({lines} lines = "
            f"{counts_per_rev} counts/rev), limit switches E1/E2, RS232 multi-drop."
        ),
        parameters=parameters,
        channels=channels,
        flags=flags,
        plots=plots,
        commands=commands,
        console=ConsoleDescriptor(
            help=(
                "Lines go to this module as typed (spaces removed; the module ignores "
                "them). Replies of rep, rrss and rrsyscon span several lines."
            ),
            multiline_commands=list(codec.MULTILINE_COMMANDS),
            examples=["rp", "rss", "rrss", "rep", "id", "qp"],
            syntax="letters",
            rules=console_rules(),
        ),
        stop=StopEffect(
            summary="SLAP2: brakes at full power in pm and holds there",
            motor_powered=True,
            sends="pm (from vm) or st + pm (from pm), ahead of anything queued",
            category=2,
            loop_failed="loop not working: spwm 0 (winding shorted), st once at rest",
            power_off_command="power_off",
            gentler=["jog_stop", "hold"],
        ),
        loop=LoopSignals(
            position_channel="position",
            following_error_channel="following_error",
            moving_flags=["move", "vm"],
            reference_channel="setpoint",
            current_limit_flag="oc",
            closed_loop_flags=["pm", "vm"],
            # ~18° of a 2048-count revolution: far above the ringing of a loop that
            # works (a few tens of counts), far below the loaded module's limit cycle
            # with the factory gains (±1900).
            oscillation_counts=100,
            rest_velocity=200,
        ),
        jog=JogDescriptor(
            minus=JogPress(command="jog", args={"direction": -1}),
            plus=JogPress(command="jog", args={"direction": 1}),
            release="jog_stop",
            title="Hold to run at sv (pm + ma); release decelerates with sa and holds",
        ),
        autotune=True,
        # the velocity step writes it for the test (axis.py bench_plan)
        bench_velocity_parameter="velocity",
        twin=TwinDescriptor(
            counts_per_rev=counts_per_rev,
            setpoint_channel="setpoint",
            moving_flag="move",
            in_position_flag="inpos",
            switch_flags=["limit1", "limit2"],
        ),
    )
