"""The EP7047-1032 device descriptor: CoE settings, telemetry, flags and commands as data.

Texts paraphrase ``shared/spec/ep7047.md`` and the vendor manual (German) in English.
Units: positions in counts of the drive's counter, velocities of the process data in
basis points of the speed range 0x8012:05 (10000 = 100 %), ramps in ms for 0..100 %
of the speed range. The conversions to steps/s and turns use the link's
``speed_range_steps_s`` and ``counts_per_rev``.

The tables at the top (``PARAMETER_SDO``, ``POS_FLAGS``, ...) are shared with the driver
(``servotune.devices.ep7047.link``) so that what the UI is told and what the driver reports
cannot drift apart.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final

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
    ParameterConstraint,
    ParameterDescriptor,
    PlotDescriptor,
    StopEffect,
    TwinDescriptor,
)
from servotune.devices.ep7047 import NAME, codec
from servotune.devices.ep7047.codec import PosDiag, PosStatus, SdoObject, StartType, StmStatus

MODEL: Final = "Beckhoff EP7047-1032"

# --- parameters <-> CoE -------------------------------------------------------------------

# Descriptor parameter -> its CoE entry (one value, one SDO). The names are those of
# ``codec.PosSettings`` except ``default_start_type`` (PosSettings.start_type).
PARAMETER_SDO: Final[Mapping[str, SdoObject]] = {
    "velocity_min_bp": codec.VELOCITY_MIN,
    "velocity_max_bp": codec.VELOCITY_MAX,
    "acceleration_pos_ms": codec.ACCELERATION_POS,
    "acceleration_neg_ms": codec.ACCELERATION_NEG,
    "deceleration_pos_ms": codec.DECELERATION_POS,
    "deceleration_neg_ms": codec.DECELERATION_NEG,
    "emergency_deceleration_ms": codec.EMERGENCY_DECELERATION,
    "calibration_position_counts": codec.CALIBRATION_POSITION,
    "calibration_velocity_towards_cam_bp": codec.CALIBRATION_VELOCITY_TOWARDS_CAM,
    "calibration_velocity_off_cam_bp": codec.CALIBRATION_VELOCITY_OFF_CAM,
    "target_window_counts": codec.TARGET_WINDOW,
    "in_target_timeout_ms": codec.IN_TARGET_TIMEOUT,
    "modulo_factor_counts": codec.MODULO_FACTOR,
    "modulo_tolerance_window_counts": codec.MODULO_TOLERANCE_WINDOW,
    "default_start_type": codec.DEFAULT_START_TYPE,
}
# One descriptor parameter of kind "bits" for the two BOOLEANs 0x8021:13 / 0x8021:14.
INVERSION_PARAMETER: Final = "calibration_search_inversion"
INVERSION_BITS: Final[Mapping[int, SdoObject]] = {
    0: codec.INVERT_CALIBRATION_CAM_SEARCH,
    1: codec.INVERT_SYNC_IMPULSE_SEARCH,
}
# Start types that make no sense as the default start type (0x8021:01): the driver
# refuses them there. A _CHANGE type only changes a running move.
NOT_A_DEFAULT_START_TYPE: Final = codec.CHANGE_START_TYPES

# --- telemetry ------------------------------------------------------------------------------

CHANNELS: Final = ("position", "target", "velocity", "drive_time", "drive_state")

# Flag name -> bit of the POS status word (0x6020:01..08).
POS_FLAGS: Final[Mapping[str, PosStatus]] = {
    "busy": PosStatus.BUSY,
    "in_target": PosStatus.IN_TARGET,
    "warning": PosStatus.WARNING,
    "error": PosStatus.ERROR,
    "calibrated": PosStatus.CALIBRATED,
    "accelerate": PosStatus.ACCELERATE,
    "decelerate": PosStatus.DECELERATE,
    "ready_to_execute": PosStatus.READY_TO_EXECUTE,
}
# Flag name -> bit of the STM status word (0x6010).
STM_FLAGS: Final[Mapping[str, StmStatus]] = {
    "stm_ready_to_enable": StmStatus.READY_TO_ENABLE,
    "stm_ready": StmStatus.READY,
    "stm_warning": StmStatus.WARNING,
    "stm_error": StmStatus.ERROR,
    "moving_positive": StmStatus.MOVING_POSITIVE,
    "moving_negative": StmStatus.MOVING_NEGATIVE,
    "torque_reduced": StmStatus.TORQUE_REDUCED,
    "motor_stall": StmStatus.MOTOR_STALL,
    "digital_input_1": StmStatus.DIGITAL_INPUT_1,
    "digital_input_2": StmStatus.DIGITAL_INPUT_2,
    "stm_sync_error": StmStatus.SYNC_ERROR,
}
# Flag name -> bit of the POS diagnosis (0x9020:01, read over CoE when Warning is set).
DIAG_FLAGS: Final[Mapping[str, PosDiag]] = {
    "command_rejected": PosDiag.COMMAND_REJECTED,
    "command_aborted": PosDiag.COMMAND_ABORTED,
    "target_overrun": PosDiag.TARGET_OVERRUN,
}
# Output bits servotune holds (what the drive is told), streamed as flags too.
OUTPUT_FLAGS: Final = ("enable_out", "execute_out", "emergency_stop_out")

# --- commands ---------------------------------------------------------------------------

START_TYPE_TEXTS: Final[Mapping[StartType, str]] = {
    StartType.ABSOLUTE: "Go to the target position.",
    StartType.RELATIVE: "Go to the actual position + target (a distance).",
    StartType.ENDLESS_PLUS: (
        "Run positive at the velocity until Halt or STOP; the target is ignored, no In-Target."
    ),
    StartType.ENDLESS_MINUS: (
        "Run negative at the velocity until Halt or STOP; the target is ignored, no In-Target."
    ),
    StartType.ADDITIVE: (
        "Go to the last target + target: after a stall or an emergency stop the actual "
        "position does not matter."
    ),
    StartType.ABSOLUTE_CHANGE: (
        "While a move runs: new absolute target (and velocity, ramps). Rejected at "
        "standstill and while accelerating."
    ),
    StartType.RELATIVE_CHANGE: (
        "While a move runs: actual position (moving, so never exact) + target. Rejected "
        "at standstill and while accelerating."
    ),
    StartType.ADDITIVE_CHANGE: (
        "While a move runs: the active target + target. Rejected at standstill and while "
        "accelerating."
    ),
    StartType.MODULO_SHORT: (
        "Shortest way to the modulo position; the target must be in 0 .. modulo factor - 1."
    ),
    StartType.MODULO_SHORT_EXT: "As MODULO_SHORT, ignoring the modulo tolerance window.",
    StartType.MODULO_PLUS: (
        "Positive way to the modulo position; each whole modulo factor in the target adds a turn."
    ),
    StartType.MODULO_PLUS_EXT: "As MODULO_PLUS, ignoring the modulo tolerance window.",
    StartType.MODULO_MINUS: (
        "Negative way to the modulo position; each whole modulo factor in the target adds a turn."
    ),
    StartType.MODULO_MINUS_EXT: "As MODULO_MINUS, ignoring the modulo tolerance window.",
    StartType.MODULO_CURRENT: "To the modulo position in the last direction of travel.",
    StartType.MODULO_CURRENT_EXT: "As MODULO_CURRENT, ignoring the modulo tolerance window.",
    StartType.CALI_PLC_CAM: (
        "Calibrate on the cam (digital input 1): onto it, off it, then the counter is "
        "set to the calibration position."
    ),
    StartType.CALI_HW_SYNC: (
        "Calibrate on the cam and the C-track pulse: after leaving the cam, on to the "
        "next sync pulse (the accurate one)."
    ),
    StartType.SET_CALIBRATION: "Set Calibrated by hand; nothing moves.",
    StartType.SET_CALIBRATION_AUTO: (
        "Only as default start type: Calibrated at the first Enable edge. Refused here; "
        "use the 'Calibrated at Enable' command."
    ),
    StartType.CLEAR_CALIBRATION: "Clear Calibrated; nothing moves.",
}
assert set(START_TYPE_TEXTS) == set(StartType)

# Calibration commands -> the start type they execute (SET_CALIBRATION_AUTO is not one:
# its command writes the default start type 0x8021:01).
CALIBRATION_COMMANDS: Final[Mapping[str, StartType]] = {
    "cali_plc_cam": StartType.CALI_PLC_CAM,
    "cali_hw_sync": StartType.CALI_HW_SYNC,
    "set_calibration": StartType.SET_CALIBRATION,
    "clear_calibration": StartType.CLEAR_CALIBRATION,
}

VELOCITY_MAX_BP: Final = codec.SPEED_RANGE_FULL_SCALE_BP
RAMP_MAX_MS: Final = codec.UINT16_MAX


def _sdo_set(obj: SdoObject) -> str:
    return f"SDO 0x{obj.index:04X}:{obj.subindex:02X} := {{value}}"


def _sdo_read(obj: SdoObject) -> str:
    return f"SDO 0x{obj.index:04X}:{obj.subindex:02X}"


def console_rules() -> list[ConsoleRule]:
    """What the console's CoE lines do: a line without '= value' reads its object; a
    write of an object is a write of the parameter it holds (or of a setting the
    descriptor does not show: still a parameter write), a read-only one only reads."""
    holder = {(o.index, o.subindex): name for name, o in PARAMETER_SDO.items()}
    for obj in INVERSION_BITS.values():
        holder[(obj.index, obj.subindex)] = INVERSION_PARAMETER
    rules = [ConsoleRule(words=["list", "help"], effect="read")]
    for obj in codec.SDO_OBJECTS:
        word = f"0x{obj.index:04x}:{obj.subindex:02x}"
        if not obj.writable:
            rules.append(ConsoleRule(words=[word], effect="read"))
            continue
        name = holder.get((obj.index, obj.subindex))
        rules.append(ConsoleRule(words=[word], effect="write", parameters=[name] if name else []))
    return rules


def _hex(code: int) -> str:
    return f"0x{code:04X}"


def _jog_press(start_type: StartType) -> JogPress:
    """A jog direction: an endless move at 2000 bp (20 % of the speed range)."""
    args = {"target": 0, "velocity": 2000, "acceleration_ms": 500, "deceleration_ms": 500}
    return JogPress(command="execute_move", args={"start_type": int(start_type), **args})


def ep7047_descriptor(speed_range_steps_s: int, counts_per_rev: int) -> DeviceDescriptor:
    """The descriptor of one EP7047-1032 axis.

    ``speed_range_steps_s`` is the drive's speed range (0x8012:05) in full steps/s: it
    scales every velocity (10000 bp = 100 % = that many steps/s). ``counts_per_rev`` is
    what one motor turn reads on the counter (4 x encoder lines with an encoder).
    """
    if speed_range_steps_s <= 0 or counts_per_rev <= 0:
        raise ValueError("speed range and counts per revolution must be positive")
    steps_s_per_bp = speed_range_steps_s / VELOCITY_MAX_BP
    percent = Conversion(unit="%", factor=0.01, digits=2)
    steps_s = Conversion(unit="steps/s", factor=steps_s_per_bp, digits=1)
    revs = Conversion(unit="rev", factor=1 / counts_per_rev, digits=3)
    deg = Conversion(unit="°", factor=360 / counts_per_rev, digits=2)
    range_text = (
        f"10000 = 100 % of the speed range = {speed_range_steps_s} full steps/s (0x8012:05)."
    )

    def velocity_parameter(
        name: str, label: str, default: int, minimum: int, text: str, group: str = "velocity"
    ) -> ParameterDescriptor:
        obj = PARAMETER_SDO[name]
        return ParameterDescriptor(
            name=name,
            label=label,
            unit="bp",
            minimum=minimum,
            maximum=VELOCITY_MAX_BP,
            default=default,
            persisted=True,
            group=group,
            description=f"{text} {range_text}",
            set_command=_sdo_set(obj),
            read_command=_sdo_read(obj),
            conversions=[percent, steps_s],
        )

    def ramp_parameter(name: str, label: str, default: int, text: str) -> ParameterDescriptor:
        obj = PARAMETER_SDO[name]
        return ParameterDescriptor(
            name=name,
            label=label,
            unit="ms",
            minimum=0,
            maximum=RAMP_MAX_MS,
            default=default,
            persisted=True,
            group="ramps",
            description=(
                f"{text} Time for 0 -> 100 % of the speed range ({speed_range_steps_s} "
                "steps/s); to 50 % takes half as long. Used when a move's own "
                "acceleration/deceleration is 0."
            ),
            set_command=_sdo_set(obj),
            read_command=_sdo_read(obj),
            slider_maximum=5000,
        )

    start_type_list = ", ".join(
        f"{int(s)} {s.name}" for s in StartType if s not in NOT_A_DEFAULT_START_TYPE
    )
    parameters = [
        velocity_parameter(
            "velocity_min_bp",
            "Velocity min.",
            100,
            0,
            "After the braking ramp (which starts 0.5 % early) the drive creeps into the "
            "target at this velocity: low enough to stop abruptly without losing steps.",
        ),
        velocity_parameter(
            "velocity_max_bp",
            "Velocity max.",
            10000,
            1,
            "Upper limit of every move's velocity: a faster move is capped to it.",
        ),
        ramp_parameter("acceleration_pos_ms", "Acceleration pos.", 1000, "Positive direction."),
        ramp_parameter("acceleration_neg_ms", "Acceleration neg.", 1000, "Negative direction."),
        ramp_parameter("deceleration_pos_ms", "Deceleration pos.", 1000, "Positive direction."),
        ramp_parameter("deceleration_neg_ms", "Deceleration neg.", 1000, "Negative direction."),
        ParameterDescriptor(
            name="emergency_deceleration_ms",
            label="Emergency deceleration",
            unit="ms",
            minimum=0,
            maximum=RAMP_MAX_MS,
            default=100,
            persisted=True,
            group="ramps",
            description=(
                "Deceleration (both directions) while the Emergency stop output is set "
                "(Emergency stop and STOP), in ms for 100 % of the speed range."
            ),
            set_command=_sdo_set(codec.EMERGENCY_DECELERATION),
            read_command=_sdo_read(codec.EMERGENCY_DECELERATION),
            slider_maximum=2000,
        ),
        ParameterDescriptor(
            name="target_window_counts",
            label="Target window",
            unit="counts",
            minimum=0,
            maximum=codec.UINT16_MAX,
            default=10,
            persisted=True,
            group="in-target",
            description="In-Target is set when the motor comes to rest within ± this window.",
            set_command=_sdo_set(codec.TARGET_WINDOW),
            read_command=_sdo_read(codec.TARGET_WINDOW),
            conversions=[deg],
            slider_maximum=1000,
        ),
        ParameterDescriptor(
            name="in_target_timeout_ms",
            label="In-Target timeout",
            unit="ms",
            minimum=0,
            maximum=codec.UINT16_MAX,
            default=1000,
            persisted=True,
            group="in-target",
            description=(
                "If the motor is not in the target window this long after the trajectory "
                "ended, In-Target stays 0 (only Busy falling tells). Calibration waits "
                "this long before it sets the counter."
            ),
            set_command=_sdo_set(codec.IN_TARGET_TIMEOUT),
            read_command=_sdo_read(codec.IN_TARGET_TIMEOUT),
            slider_maximum=5000,
        ),
        ParameterDescriptor(
            name="modulo_factor_counts",
            label="Modulo factor",
            unit="counts",
            minimum=0,
            maximum=codec.INT32_MAX,
            default=0,
            persisted=True,
            group="modulo",
            description=(
                "The period of modulo moves (e.g. one turn = "
                f"{counts_per_rev} counts). 0: modulo start types end in Error."
            ),
            set_command=_sdo_set(codec.MODULO_FACTOR),
            read_command=_sdo_read(codec.MODULO_FACTOR),
            conversions=[revs, deg],
            slider_maximum=4 * counts_per_rev,
        ),
        ParameterDescriptor(
            name="modulo_tolerance_window_counts",
            label="Modulo tolerance window",
            unit="counts",
            minimum=0,
            maximum=codec.INT32_MAX,
            default=0,
            persisted=True,
            group="modulo",
            description=(
                "± window around the modulo set position: a start just past the target "
                "(inside it) moves back a little instead of a whole extra turn (not the "
                "_EXT start types)."
            ),
            set_command=_sdo_set(codec.MODULO_TOLERANCE_WINDOW),
            read_command=_sdo_read(codec.MODULO_TOLERANCE_WINDOW),
            conversions=[deg],
            slider_maximum=max(counts_per_rev // 8, 10),
        ),
        ParameterDescriptor(
            name="default_start_type",
            label="Default start type",
            unit="",
            minimum=int(min(StartType)),
            maximum=int(max(StartType)),
            default=int(StartType.ABSOLUTE),
            persisted=True,
            group="features",
            description=(
                "0x8021:01, used when a master sends start type 0 (servotune always sends "
                "one) and at the first Enable edge for SET_CALIBRATION_AUTO. Decimal "
                f"codes: {start_type_list}. _CHANGE types are refused here."
            ),
            set_command=_sdo_set(codec.DEFAULT_START_TYPE),
            read_command=_sdo_read(codec.DEFAULT_START_TYPE),
            slider=False,
            choices=[
                Choice(value=int(s), label=s.name, description=START_TYPE_TEXTS[s])
                for s in StartType
                if s not in NOT_A_DEFAULT_START_TYPE
            ],
        ),
        ParameterDescriptor(
            name="calibration_position_counts",
            label="Calibration position",
            unit="counts",
            minimum=codec.INT32_MIN,
            maximum=codec.INT32_MAX,
            default=0,
            persisted=True,
            group="calibration",
            description="Loaded into the counter when a calibration ends.",
            set_command=_sdo_set(codec.CALIBRATION_POSITION),
            read_command=_sdo_read(codec.CALIBRATION_POSITION),
            conversions=[revs, deg],
            slider=False,
        ),
        velocity_parameter(
            "calibration_velocity_towards_cam_bp",
            "Calibration velocity (towards cam)",
            100,
            0,
            "Velocity of a calibration while it drives onto the cam (no ramp).",
            group="calibration",
        ),
        velocity_parameter(
            "calibration_velocity_off_cam_bp",
            "Calibration velocity (off cam)",
            10,
            0,
            "Velocity while it drives off the cam and on to the C-track pulse (no ramp).",
            group="calibration",
        ),
        ParameterDescriptor(
            name=INVERSION_PARAMETER,
            label="Calibration search directions",
            unit="",
            minimum=0,
            maximum=3,
            default=0,
            persisted=True,
            group="calibration",
            description=(
                "Relative to the positive direction: bit 0 inverts the search for the cam "
                "(0x8021:13), bit 1 the direction off the cam / towards the sync pulse "
                "(0x8021:14)."
            ),
            set_command=("SDO 0x8021:13 := bit 0 of {value}; SDO 0x8021:14 := bit 1 of {value}"),
            read_command="SDO 0x8021:13, 0x8021:14",
            kind="bits",
            bits=[
                BitDescriptor(
                    bit=0,
                    name="invert_calibration_cam_search",
                    label="invert cam search",
                    description="Drive onto the cam in the negative direction.",
                ),
                BitDescriptor(
                    bit=1,
                    name="invert_sync_impulse_search",
                    label="invert sync search",
                    description="Drive off the cam / to the C-track pulse negatively.",
                ),
            ],
            slider=False,
        ),
    ]

    channels = [
        ChannelDescriptor(
            name="position",
            label="Actual position",
            unit="counts",
            description="0x6020:11 Actual position, every EtherCAT cycle.",
            conversions=[revs, deg],
        ),
        ChannelDescriptor(
            name="target",
            label="Target (set position)",
            unit="counts",
            description=(
                "Target of the current or last move, computed by servotune from the start "
                "type (the drive does not report it): absolute, actual + distance, last "
                "target + distance, or the modulo rule. Empty for ENDLESS and calibration."
            ),
            conversions=[revs, deg],
        ),
        ChannelDescriptor(
            name="velocity",
            label="Actual velocity",
            unit="steps/s",
            description=(
                "0x6020:21 Actual velocity (bp of the speed range) in full steps/s; "
                f"10000 bp = {speed_range_steps_s} steps/s."
            ),
            conversions=[Conversion(unit="%", factor=100 / speed_range_steps_s, digits=2)],
        ),
        ChannelDescriptor(
            name="drive_time",
            label="Actual drive time",
            unit="ms",
            description="0x6020:22: time since the current or last move started.",
        ),
        ChannelDescriptor(
            name="drive_state",
            label="Drive state (sampled)",
            unit="id",
            description=(
                "0x9020:03 State (drive controller), read over CoE between cycles: "
                + ", ".join(f"{s.value:#06x} {s.name}" for s in codec.DriveState)
                + ". Sampled: states that last one 250 µs cycle are usually not seen."
            ),
            value_names={str(s.value): s.name for s in codec.DriveState},
        ),
    ]

    pos_texts: dict[str, tuple[str, str, str]] = {
        "busy": ("Busy", "A move or command is being executed (0x6020:01).", "info"),
        "in_target": (
            "In-Target",
            "The last move ended in the target window within the In-Target timeout.",
            "info",
        ),
        "warning": (
            "Warning",
            "A diagnosis bit is set (Command rejected, aborted, or Target overrun).",
            "warning",
        ),
        "error": (
            "Error",
            "The move or command failed (e.g. no Enable, bad start type, velocity 0, modulo "
            "target out of range). Cleared by the next start or Reset error.",
            "fault",
        ),
        "calibrated": ("Calibrated", "The axis has been calibrated (or set so).", "info"),
        "accelerate": ("Accelerate", "The drive is ramping up.", "info"),
        "decelerate": ("Decelerate", "The drive is ramping down.", "info"),
        "ready_to_execute": (
            "Ready to execute",
            "Enabled, not Busy, no emergency stop: a move can start.",
            "info",
        ),
    }
    stm_texts: dict[str, tuple[str, str, str]] = {
        "stm_ready_to_enable": (
            "STM ready to enable",
            "The driver stage can be enabled (0x6010:01).",
            "info",
        ),
        "stm_ready": ("STM ready", "The driver stage is enabled and powers the motor.", "info"),
        "stm_warning": (
            "STM warning",
            "Driver stage warning (e.g. temperature, under-voltage).",
            "warning",
        ),
        "stm_error": (
            "STM error",
            "Driver stage error (e.g. over-current, no motor voltage). Reset error clears it.",
            "fault",
        ),
        "moving_positive": ("Moving +", "The motor turns in the positive direction.", "info"),
        "moving_negative": ("Moving −", "The motor turns in the negative direction.", "info"),
        "torque_reduced": ("Torque reduced", "The reduced (holding) current is active.", "info"),
        "motor_stall": (
            "Motor stall",
            "The drive detected a stall: steps were lost, the position is not reliable.",
            "fault",
        ),
        "digital_input_1": ("Input 1 (cam)", "Digital input 1: the calibration cam.", "info"),
        "digital_input_2": ("Input 2", "Digital input 2.", "info"),
        "stm_sync_error": ("Sync error", "The process data arrived out of sync.", "warning"),
    }
    diag_texts: dict[str, tuple[str, str, str]] = {
        "command_rejected": (
            "Command rejected",
            "A dynamic target change (_CHANGE) could not be taken: at standstill or while "
            "accelerating (0xA020:01).",
            "warning",
        ),
        "command_aborted": (
            "Command aborted",
            "The move ended early: internal error, Emergency stop, or Execute dropped (0xA020:02).",
            "warning",
        ),
        "target_overrun": (
            "Target overrun",
            "A late change forced a reversal past the new target (0xA020:03).",
            "warning",
        ),
    }
    flags = [
        FlagDescriptor(
            name=name,
            label=pos_texts[name][0],
            description=pos_texts[name][1],
            bit=bit.bit_length() - 1,
            source="0x6020 POS status",
            severity=pos_texts[name][2],  # type: ignore[arg-type]
        )
        for name, bit in POS_FLAGS.items()
    ]
    flags += [
        FlagDescriptor(
            name=name,
            label=stm_texts[name][0],
            description=stm_texts[name][1],
            bit=bit.bit_length() - 1,
            source="0x6010 STM status",
            severity=stm_texts[name][2],  # type: ignore[arg-type]
        )
        for name, bit in STM_FLAGS.items()
    ]
    flags += [
        FlagDescriptor(
            name=name,
            label=diag_texts[name][0],
            description=diag_texts[name][1] + " Read over CoE when Warning rises.",
            bit=bit.bit_length() - 1,
            source="0x9020:01 POS status word",
            severity=diag_texts[name][2],  # type: ignore[arg-type]
        )
        for name, bit in DIAG_FLAGS.items()
    ]
    flags += [
        FlagDescriptor(
            name="enable_out",
            label="Enable (out)",
            description="servotune holds the STM Enable output (0x7010:01).",
            bit=0,
            source="0x7010 STM control (output)",
        ),
        FlagDescriptor(
            name="execute_out",
            label="Execute (out)",
            description=(
                "servotune holds Execute (0x7020:01): raised to start, dropped when Busy "
                "has risen and fallen."
            ),
            bit=0,
            source="0x7020 POS control (output)",
        ),
        FlagDescriptor(
            name="emergency_stop_out",
            label="Emergency stop (out)",
            description="The Emergency stop output (0x7020:02) is set.",
            bit=1,
            source="0x7020 POS control (output)",
            severity="warning",
        ),
    ]

    plots = [
        PlotDescriptor(
            name="position", label="Position", unit="counts", series=["position", "target"]
        ),
        PlotDescriptor(name="velocity", label="Velocity", unit="steps/s", series=["velocity"]),
        PlotDescriptor(
            name="drive_state",
            label="Drive state (0x9020:03, sampled)",
            unit="id",
            series=["drive_state"],
            kind="states",
        ),
        PlotDescriptor(
            name="flags",
            label="Flags",
            unit="",
            series=[*POS_FLAGS, *DIAG_FLAGS, "execute_out"],
            kind="flags",
        ),
    ]

    start_type_choices = [
        Choice(value=int(s), label=f"{s.name} ({_hex(s)})", description=START_TYPE_TEXTS[s])
        for s in StartType
    ]
    calibration_texts = {
        "cali_plc_cam": (
            "Calibrate (cam)",
            "CALI_PLC_CAM: onto the cam (digital input 1), off it, wait the In-Target "
            "timeout, counter := Calibration position. The cam is polled, so the result "
            "has a small systematic error.",
        ),
        "cali_hw_sync": (
            "Calibrate (cam + C track)",
            "CALI_HW_SYNC: as the cam calibration, then on to the next C-track pulse: the "
            "pulse becomes the Calibration position (accurate).",
        ),
        "set_calibration": ("Set calibrated", "SET_CALIBRATION: set Calibrated by hand."),
        "clear_calibration": ("Clear calibrated", "CLEAR_CALIBRATION: clear Calibrated."),
    }
    calibration_confirm = (
        "The axis drives at the calibration velocities until it finds the cam (digital "
        "input 1) - without a cam it runs on. Keep a hand on STOP."
    )
    commands = [
        CommandDescriptor(
            name="stop",
            label="STOP",
            description=(
                "Emergency stop with the emergency deceleration on the next EtherCAT cycle "
                "(ahead of anything queued, which is discarded), then Enable off: the motor "
                "has no holding torque afterwards."
            ),
            group="stop",
        ),
        CommandDescriptor(
            name="power_off",
            label="Power off",
            description=(
                "Enable off at once, whatever the axis does (stop category 0): the motor "
                "is unpowered and a moving axis coasts to a stop on its load, unbraked "
                "(STOP ramps it down first: shorter)."
            ),
            group="stop",
        ),
        CommandDescriptor(
            name="emergency_stop",
            label="Emergency stop",
            description=(
                "Set the Emergency stop output: the drive ramps down with the emergency "
                "deceleration and aborts the move (Command aborted); Enable stays on, so "
                "the motor keeps its holding torque. Released at standstill."
            ),
            group="stop",
        ),
        CommandDescriptor(
            name="halt",
            label="Halt",
            description=(
                "Drop Execute: the drive ramps down with the move's deceleration. Ends an "
                "ENDLESS move; aborts a positioning move or calibration (Command aborted)."
            ),
            group="stop",
        ),
        CommandDescriptor(
            name="enable",
            label="Enable",
            description=(
                "Set the STM Enable output and hold it: the driver stage powers the motor. "
                "Needed for every move."
            ),
            group="mode",
            active_flag="enable_out",
        ),
        CommandDescriptor(
            name="disable",
            label="Disable",
            description=(
                "Drop Enable: the motor is unpowered (no holding torque). While moving, "
                "the move ends with Error and the axis coasts to a stop on its load."
            ),
            group="mode",
        ),
        CommandDescriptor(
            name="reset_error",
            label="Reset error",
            description=(
                "Pulse the STM Reset output: clears a latched Error, Warning and the "
                "diagnosis. Not while Busy."
            ),
            group="other",
        ),
        CommandDescriptor(
            name="execute_move",
            label="Execute",
            description=(
                "Write target, velocity, start type and ramps, raise Execute and hold it "
                "until Busy has risen and fallen. A _CHANGE start type changes the running "
                "move (Execute stays high). Refused when not enabled or while a move runs."
            ),
            group="motion",
            arguments=[
                ArgumentDescriptor(
                    name="start_type",
                    label="Start type",
                    minimum=int(min(StartType)),
                    maximum=int(max(StartType)),
                    default=int(StartType.ABSOLUTE),
                    choices=start_type_choices,
                ),
                ArgumentDescriptor(
                    name="target",
                    label="Target / distance",
                    unit="counts",
                    minimum=codec.INT32_MIN,
                    maximum=codec.INT32_MAX,
                    default=counts_per_rev,
                    required=True,
                ),
                ArgumentDescriptor(
                    name="velocity",
                    label=f"Velocity (10000 = {speed_range_steps_s} steps/s)",
                    unit="bp",
                    # 0 is an Error on the drive for every move; calibration and the
                    # instant types ignore the value, so 1 costs them nothing.
                    minimum=1,
                    maximum=VELOCITY_MAX_BP,
                    default=2000,
                ),
                ArgumentDescriptor(
                    name="acceleration_ms",
                    label="Acceleration (ms to 100 %, 0 = setting)",
                    unit="ms",
                    minimum=0,
                    maximum=RAMP_MAX_MS,
                    default=500,
                ),
                ArgumentDescriptor(
                    name="deceleration_ms",
                    label="Deceleration (ms from 100 %, 0 = setting)",
                    unit="ms",
                    minimum=0,
                    maximum=RAMP_MAX_MS,
                    default=500,
                ),
            ],
            abort_command="halt",
        ),
    ]
    for name, start_type in CALIBRATION_COMMANDS.items():
        label, text = calibration_texts[name]
        moves = start_type in (StartType.CALI_PLC_CAM, StartType.CALI_HW_SYNC)
        commands.append(
            CommandDescriptor(
                name=name,
                label=label,
                description=text,
                group="calibration",
                confirm=calibration_confirm if moves else None,
                abort_command="halt" if moves else None,
            )
        )
    commands += [
        CommandDescriptor(
            name="set_calibration_auto",
            label="Calibrated at Enable",
            description=(
                "Write SET_CALIBRATION_AUTO (0x6E01) as the default start type 0x8021:01: "
                "the drive sets Calibrated at the first rising edge of Enable (after its "
                "power-on). The manual's way for axes that cannot be calibrated."
            ),
            group="calibration",
        ),
        CommandDescriptor(
            name="restore_parameters",
            label="Re-apply last settings",
            description=(
                "Write the last settings servotune applied or read to this drive again "
                "(after it was replaced or reset)."
            ),
            group="persist",
        ),
    ]

    return DeviceDescriptor(
        device=NAME,
        model=MODEL,
        title="EP7047-1032 stepper drive (positioning interface)",
        summary=(
            "EtherCAT stepper drive with encoder input, driven through its built-in "
            "positioning interface (process data every cycle, settings over CoE). "
            f"Velocities: 10000 bp = {speed_range_steps_s} full steps/s; {counts_per_rev} "
            "counts/rev. The drive state (0x9020:03) runs every 250 µs and is only "
            "sampled between EtherCAT cycles: short states (START, TARGET, ...) may not "
            "be seen."
        ),
        parameters=parameters,
        channels=channels,
        flags=flags,
        plots=plots,
        commands=commands,
        console=ConsoleDescriptor(
            help=(
                "CoE access to the positioning objects: '0x8020:0E' reads, "
                "'0x8020:0E = 4096' writes and reads back, 'list' names them. Only the "
                "objects of the positioning interface; writes bypass the parameter ranges "
                "but not the data type."
            ),
            examples=["list", "0x9020:03", "0x9020:01", "0x8020:0E", "0x8020:02 = 5000"],
            syntax="object",
            rules=console_rules(),
        ),
        stop=StopEffect(
            summary="EP7047: emergency ramp, then no holding torque",
            motor_powered=False,
            sends="Emergency stop output on the next cycle, then Enable off",
            category=1,
            loop_failed="an open-loop stepper: no position loop to fail, the ramp as always",
            power_off_command="power_off",
            gentler=["emergency_stop", "halt"],
        ),
        jog=JogDescriptor(
            minus=_jog_press(StartType.ENDLESS_MINUS),
            plus=_jog_press(StartType.ENDLESS_PLUS),
            release="halt",
            title="Hold: endless move at 2000 bp; release halts with the move's deceleration",
        ),
        constraints=[
            ParameterConstraint(
                lower="velocity_min_bp",
                upper="velocity_max_bp",
                message="the creep velocity into the target must not exceed the maximum velocity",
            ),
        ],
        twin=TwinDescriptor(
            counts_per_rev=counts_per_rev,
            target_channel="target",
            moving_flag="busy",
            in_position_flag="in_target",
            switch_flags=["digital_input_1"],
        ),
    )
