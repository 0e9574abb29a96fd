"""The Z1100 axis descriptor: one per motor of the three-axis chip, as data for the UI.

Texts paraphrase the vendor manual (Turkish) and ``shared/spec/z1100.md`` in English.
Speeds are counts/s and accelerations counts/s² on the wire; rpm is shown from the
encoder's counts per revolution (4 x lines).
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
from servotune.devices.z1100 import NAME, codec

GAINS = {
    "k": (
        "K",
        "Proportional gain. Higher: shorter response and less tracking error, "
        "until it oscillates. K = 0: the motor never turns.",
    ),
    "a": ("A", "Derivative action on the forward path (damps the response)."),
    "b": ("B", "Tachometric (velocity) feedback: damps, slows the response."),
}

# Console: the Set commands that write descriptor parameters, and those that are a
# descriptor command (the Get commands only read). SetBaud re-clocks the chip's line:
# a configuration change the link loses the chip over, as privileged as SetFlash.
_CONSOLE_WRITES = {
    codec.Command.SET_KABH: [f"kabh_{g}" for g in "kab"],
    codec.Command.SET_KABD: [f"kabd_{g}" for g in "kab"],
    codec.Command.SET_VMAX: ["vmax"],
    codec.Command.SET_ACC: ["acc"],
    codec.Command.SET_STM: ["stm"],
    codec.Command.SET_HVM: ["hvm"],
    codec.Command.SET_HAC: ["hac"],
    codec.Command.SET_LIMIT: ["limit"],
    codec.Command.SET_CAB: ["cab"],
    codec.Command.SET_BUSY: ["busy"],
}
_CONSOLE_COMMANDS = {
    codec.Command.SET_ESTOP: "stop",
    codec.Command.SET_STOP: "decelerate",
    codec.Command.SET_JOB: "free",  # job 0 frees the shaft; 2 and 3 prepare a move
    codec.Command.SET_TARGET: "go_to_target",
    codec.Command.SET_START: "go_to_target",
    codec.Command.SET_CLR: "clear_errors",
    codec.Command.SET_ZERO: "home",
    codec.Command.SET_FLASH: "save_flash",
}


def console_rules() -> list[ConsoleRule]:
    """What every Z1100 console command does (its name, any case, is the first word)."""
    names = {command: codec.COMMANDS[command].name.lower() for command in codec.Command}
    rules = [
        ConsoleRule(words=[names[c] for c in codec.Command if c.is_get], effect="read"),
        ConsoleRule(words=[names[codec.Command.SET_BAUD]], effect="persist"),
    ]
    rules += [
        ConsoleRule(words=[names[c]], effect="write", parameters=parameters)
        for c, parameters in _CONSOLE_WRITES.items()
    ]
    rules += [
        ConsoleRule(words=[names[c]], effect="command", command=command)
        for c, command in _CONSOLE_COMMANDS.items()
    ]
    return rules


CAB_BITS = [
    BitDescriptor(
        bit=0,
        name="motor_reversed",
        label="motor reversed",
        description="Motor leads are reversed: the chip inverts its output.",
    ),
    BitDescriptor(
        bit=1,
        name="encoder_swapped",
        label="encoder A/B swapped",
        description="Encoder channels A and B are swapped: the chip counts the other way.",
    ),
    BitDescriptor(
        bit=2,
        name="switch_active_high",
        label="home switch reads 1",
        description="The home switch input reads 1 when pressed (normally 0).",
    ),
]

# Parameters written while the axis moves are refused by the chip (reply bits 4..6);
# the server refuses them first when it knows the axis is moving.
FORBIDDEN_WHILE_MOVING = {"vmax", "acc", "hvm", "hac", "cab"}
MOVING_COMMANDS = {"go_to_target", "constant_velocity", "home"}


def z1100_descriptor(counts_per_rev: int) -> DeviceDescriptor:
    """Descriptor of one Z1100 axis with an encoder of ``counts_per_rev`` counts."""
    rpm = Conversion(unit="rpm", factor=60 / counts_per_rev, digits=1)
    rpm_s = Conversion(unit="rpm/s", factor=60 / counts_per_rev, digits=0)
    revs = Conversion(unit="rev", factor=1 / counts_per_rev, digits=3)
    parameters: list[ParameterDescriptor] = []
    for prefix, label, when, note in (
        (
            "kabh",
            "moving",
            "while the motor moves",
            " Writing KABH also overwrites KABD (manual): write KABD after it.",
        ),
        ("kabd", "standstill", "while the motor stands still", " Usually smaller than KABH."),
    ):
        for gain, (gain_label, text) in GAINS.items():
            parameters.append(
                ParameterDescriptor(
                    name=f"{prefix}_{gain}",
                    label=f"{gain_label} ({label})",
                    unit="",
                    minimum=0,
                    maximum=codec.GAIN_MAX,
                    persisted=True,
                    group=f"gains {label} ({prefix.upper()})",
                    description=f"{text} Used {when}.{note}",
                    set_command=f"Set{prefix.upper()} {gain.upper()}={{value}}",
                    read_command=f"Get{prefix.upper()}",
                    overwrites=[f"kabd_{g}" for g in GAINS] if prefix == "kabh" else [],
                )
            )
    parameters += [
        ParameterDescriptor(
            name="vmax",
            label="Vmax",
            unit="counts/s",
            minimum=0,
            maximum=codec.POSITIVE32_MAX,
            persisted=True,
            group="profile",
            description="Cruise speed of moves and the constant-velocity job. Refused "
            "while the motor moves. 0: the motor never turns.",
            set_command="SetVmax {value}",
            read_command="GetVmax",
            conversions=[rpm],
            slider_maximum=200_000,
        ),
        ParameterDescriptor(
            name="acc",
            label="Acc",
            unit="counts/s²",
            minimum=0,
            maximum=codec.POSITIVE32_MAX,
            persisted=True,
            group="profile",
            description="Acceleration = deceleration of the trapezoid. Refused while "
            "the motor moves. Short moves never reach Vmax.",
            set_command="SetAcc {value}",
            read_command="GetAcc",
            conversions=[rpm_s],
            slider_maximum=2_000_000,
        ),
        ParameterDescriptor(
            name="limit",
            label="Error limit",
            unit="counts",
            minimum=0,
            maximum=codec.LIMIT_MAX_COUNTS,
            persisted=True,
            group="protection",
            description="Position error beyond which the chip cuts motor power (stall "
            "protection). Must be non-zero to start.",
            set_command="SetLimit {value}",
            read_command="GetLimit",
        ),
        ParameterDescriptor(
            name="stm",
            label="Sampling time (Stm)",
            unit="× 32 µs",
            minimum=1,
            maximum=codec.BYTE_MAX,
            persisted=True,
            group="loop",
            description="Servo sampling time = Stm x 32 µs (1 at power-on).",
            set_command="SetStm {value}",
            read_command="GetStm",
            conversions=[Conversion(unit="µs", factor=codec.STM_TICK_S * 1e6, digits=0)],
            slider_maximum=64,
        ),
        ParameterDescriptor(
            name="hvm",
            label="Home speed (Hvm)",
            unit="counts/s",
            minimum=0,
            maximum=codec.POSITIVE32_MAX,
            persisted=True,
            group="homing",
            description="Maximum speed while homing (SetZero). Must be non-zero to start.",
            set_command="SetHvm {value}",
            read_command="GetHvm",
            conversions=[rpm],
            slider_maximum=100_000,
        ),
        ParameterDescriptor(
            name="hac",
            label="Home acceleration (Hac)",
            unit="counts/s²",
            minimum=0,
            maximum=codec.POSITIVE32_MAX,
            persisted=True,
            group="homing",
            description="Acceleration while homing.",
            set_command="SetHac {value}",
            read_command="GetHac",
            conversions=[rpm_s],
            slider_maximum=1_000_000,
        ),
        ParameterDescriptor(
            name="cab",
            label="Wiring (Cab)",
            unit="",
            minimum=0,
            maximum=codec.CAB_MASK,
            persisted=True,
            group="wiring",
            description="Inversions for motor leads, encoder channels and the home "
            "switch. Refused while the motor moves.",
            set_command="SetCab {value}",
            read_command="GetCab",
            kind="bits",
            bits=CAB_BITS,
            slider=False,
        ),
        ParameterDescriptor(
            name="busy",
            label="Drives BUSY pin",
            unit="",
            minimum=0,
            maximum=1,
            persisted=True,
            group="wiring",
            description="This motor holds the BUSY pin until its move is done.",
            set_command="SetBusy {value}",
            read_command="GetBusy",
            slider=False,
        ),
    ]
    channels = [
        ChannelDescriptor(
            name="position",
            label="Encoder position",
            unit="counts",
            description="GetEncoder.",
            conversions=[revs],
        ),
        ChannelDescriptor(
            name="target",
            label="Target",
            unit="counts",
            description="The target of the go-to-target job (as last set).",
            conversions=[revs],
        ),
        ChannelDescriptor(
            name="setpoint",
            label="Profile position",
            unit="counts",
            description=(
                "Position + GetError: where the trapezoid is now. Empty while the error "
                "is not steady: the two are read a transaction apart, and on a ringing "
                "motor their sum is no profile position."
            ),
            conversions=[revs],
        ),
        ChannelDescriptor(
            name="following_error",
            label="Position error",
            unit="counts",
            description="GetError (signed 16-bit): profile position minus encoder.",
        ),
        ChannelDescriptor(
            name="velocity",
            label="Velocity",
            unit="counts/s",
            description="Derived from successive encoder positions.",
            conversions=[rpm],
        ),
    ]
    flags = [
        FlagDescriptor(
            name="running",
            label="running",
            source="GetStart",
            description="The motor is running a move or a velocity job (GetStart).",
        ),
        FlagDescriptor(
            name="positive",
            label="dir +",
            source="GetStart",
            description="Direction bit of the velocity job: counts increase.",
        ),
        FlagDescriptor(
            name="stopped",
            label="stopped",
            source="GetStop",
            description="Stopped by a Stop or Estop command (GetStop bits 0..2).",
        ),
        FlagDescriptor(
            name="stall",
            label="stall",
            source="GetStop",
            severity="fault",
            description="Stopped by the error limit: motor power cut (GetStop bits 4..6). "
            "Persists until Clear errors or the next start.",
        ),
        FlagDescriptor(
            name="switch",
            label="home",
            source="GetSwitch",
            severity="warning",
            description="Home switch pressed (GetSwitch).",
        ),
    ]
    plots = [
        PlotDescriptor(
            name="position",
            label="Position",
            unit="counts",
            series=["position", "setpoint", "target"],
        ),
        PlotDescriptor(
            name="following_error",
            label="Position error",
            unit="counts",
            series=["following_error"],
        ),
        PlotDescriptor(name="velocity", label="Velocity", unit="counts/s", series=["velocity"]),
        PlotDescriptor(
            name="flags",
            label="Flags",
            unit="",
            series=["running", "stall", "stopped", "switch"],
            kind="flags",
        ),
    ]
    commands = [
        CommandDescriptor(
            name="stop",
            label="STOP",
            group="stop",
            description=(
                "Estop for this motor: stops at once (a hard jolt); the controller stays "
                "on and holds the position. Stop (decelerate) is the gentle stop of the "
                "constant-velocity job."
            ),
        ),
        CommandDescriptor(
            name="power_off",
            label="Power off",
            group="stop",
            description=(
                "Job 0 at once (allowed while moving): motor power off, the shaft turns "
                "freely (stop category 0). Clears errors."
            ),
        ),
        CommandDescriptor(
            name="decelerate",
            label="Stop (decelerate)",
            group="motion",
            description="Stop: decelerate to a stop (constant-velocity job only).",
        ),
        CommandDescriptor(
            name="go_to_target",
            label="Go to",
            group="motion",
            description="Job 2 + Target + Start: a trapezoid to the target with Vmax/Acc.",
            arguments=[
                ArgumentDescriptor(
                    name="target",
                    label="Target",
                    unit="counts",
                    minimum=codec.INT32_MIN,
                    maximum=codec.INT32_MAX,
                    default=4096,
                    required=True,
                )
            ],
            target=MoveTarget(argument="target"),
        ),
        CommandDescriptor(
            name="constant_velocity",
            label="Run at Vmax",
            group="motion",
            description="Job 3 + Start: turn at constant velocity Vmax until Stop.",
            arguments=[
                ArgumentDescriptor(
                    name="direction",
                    label="Direction",
                    minimum=0,
                    maximum=1,
                    default=1,
                    choices=[
                        Choice(value=1, label="+", description="counts increase"),
                        Choice(value=0, label="−", description="counts decrease"),
                    ],
                )
            ],
        ),
        CommandDescriptor(
            name="free",
            label="Free shaft",
            group="mode",
            description="Job 0: motor power off; the shaft turns freely. Clears errors.",
        ),
        CommandDescriptor(
            name="home",
            label="Home (SetZero)",
            group="calibration",
            description="Drive onto the home switch with Hvm/Hac and zero the counter.",
        ),
        CommandDescriptor(
            name="clear_errors",
            label="Clear errors",
            group="other",
            description="Clr: clears the stall error of every motor.",
        ),
        CommandDescriptor(
            name="save_flash",
            label="Write to flash",
            group="persist",
            description="SetFlash: store all parameters of all three motors; loaded at power-on.",
            confirm="Write the parameters of all three motors to the chip's flash?",
            stores_parameters="link",
        ),
        CommandDescriptor(
            name="restore_parameters",
            label="Re-apply last settings",
            group="persist",
            description="Write the last settings servotune applied or read to this motor "
            "again (after a chip reset).",
        ),
    ]
    return DeviceDescriptor(
        device=NAME,
        model="CNC Designer Z1100",
        title="Z1100 three-axis DC servo chip",
        summary=(
            f"One of three motors; PWM+DIR to an external driver, quadrature encoder "
            f"({counts_per_rev} counts/rev), home switch, stall protection. Binary "
            "request/reply at 1200..38400 baud."
        ),
        parameters=parameters,
        channels=channels,
        flags=flags,
        plots=plots,
        commands=commands,
        # SetKABH also overwrites KABD on the chip: both sets are one group, KABH first.
        write_groups=[[f"{prefix}_{g}" for prefix in ("kabh", "kabd") for g in GAINS]],
        console=ConsoleDescriptor(
            help=(
                "A command by name with its data, e.g. 'GetKABH', 'SetVmax 20000', "
                "'SetKABH 40 10 20', 'GetStop'. The reply is decoded with its error bits."
            ),
            examples=["GetEncoder", "GetError", "GetKABH", "GetStart", "GetStop", "GetVmax"],
            syntax="word",
            rules=console_rules(),
        ),
        stop=StopEffect(
            summary="Z1100: hard stop at once, then holds under power",
            motor_powered=True,
            sends="Estop for this motor (ahead of anything queued)",
            category=2,
            loop_failed="loop not working: Job 0, motor power off at once",
            power_off_command="power_off",
            gentler=["decelerate"],
        ),
        loop=LoopSignals(
            position_channel="position",
            following_error_channel="following_error",
            moving_flags=["running"],
            # The chip's target, not position + error: GetError is read at another
            # moment than GetEncoder, so their sum scatters with a fast oscillation.
            reference_channel="target",
            # ~18° of a 2048-count revolution, as for the SLAP2.
            oscillation_counts=100,
            rest_velocity=200,
        ),
        jog=JogDescriptor(
            minus=JogPress(command="constant_velocity", args={"direction": 0}),
            plus=JogPress(command="constant_velocity", args={"direction": 1}),
            release="decelerate",
            title="Hold to run at Vmax; release decelerates with Acc and holds",
        ),
        autotune=True,
        # the velocity step writes it for the test (axis.py bench_plan)
        bench_velocity_parameter="vmax",
        twin=TwinDescriptor(
            counts_per_rev=counts_per_rev,
            setpoint_channel="setpoint",
            target_channel="target",
            moving_flag="running",
        ),
    )
