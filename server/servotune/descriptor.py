"""Device descriptors: what a device offers, as data the web UI renders.

A descriptor lists a device's parameters (with unit, range, whether the device can
persist them, and the wire commands that set and read them), its telemetry channels,
its status flags and its commands. The UI builds every axis page from this data, so a
new controller family is a new descriptor, not a new page.

Drivers build descriptors, the API serves them, and ``servotune.schema_ts`` turns these
models into TypeScript types for the web client.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class Conversion(BaseModel):
    """An alternative display unit: ``display = raw * factor``."""

    unit: str
    factor: float
    digits: int = 1


class BitDescriptor(BaseModel):
    """One bit of a bit-field parameter (e.g. a configuration word)."""

    bit: int
    name: str
    label: str
    description: str


class Choice(BaseModel):
    value: int
    label: str
    description: str


class ParameterDescriptor(BaseModel):
    """A settable device parameter.

    ``minimum``/``maximum`` are enforced by the server before anything reaches the wire.
    ``persisted`` means the device's own save command (e.g. SLAP2 ``pg``) stores it.
    """

    name: str
    label: str
    unit: str
    minimum: int
    maximum: int
    default: int | None = None
    persisted: bool = False
    group: str
    description: str
    set_command: str = Field(description="wire form, '{value}' is replaced")
    read_command: str
    conversions: list[Conversion] = []
    kind: Literal["int", "bits"] = "int"
    bits: list[BitDescriptor] = []
    slider: bool = True
    overwrites: list[str] = Field(
        default=[],
        description="parameters the device changes too when this one is written (the UI "
        "offers to write the user's values of those again)",
    )
    slider_minimum: int | None = Field(
        default=None, description="lower end of the slider when the range is much larger"
    )
    slider_maximum: int | None = Field(
        default=None, description="upper end of the slider when the range is much larger"
    )
    choices: list[Choice] = Field(
        default=[],
        description="when given, the only values allowed (e.g. codes of an enumeration)",
    )


class ChannelDescriptor(BaseModel):
    """A telemetry channel streamed over the websocket.

    ``value_names`` makes it an enumeration (e.g. a drive state): the UI shows the
    name of the value (keys are the values as decimal strings) and plots it as a
    timeline of named states.
    """

    name: str
    label: str
    unit: str
    description: str
    conversions: list[Conversion] = []
    value_names: dict[str, str] = {}


class FlagDescriptor(BaseModel):
    """A boolean status flag streamed with telemetry."""

    name: str
    label: str
    description: str
    bit: int | None = None
    source: str = ""
    severity: Literal["info", "warning", "fault"] = "info"


class PlotDescriptor(BaseModel):
    """A plot the UI draws: a group of channels sharing a y axis."""

    name: str
    label: str
    unit: str
    series: list[str]
    kind: Literal["line", "flags", "states"] = "line"


class ArgumentDescriptor(BaseModel):
    """An integer argument of a command.

    ``required``: the API needs it in every request (a target, a distance: a script
    that forgets one must not move the axis by the UI's suggestion). Otherwise it may
    be omitted and ``default`` is used, the value the UI also starts with.
    """

    name: str
    label: str
    unit: str = ""
    minimum: int
    maximum: int
    default: int = 0
    required: bool = Field(
        default=False,
        description="must be given in the API; otherwise 'default' is used when omitted",
    )
    choices: list[Choice] = []


class MoveTarget(BaseModel):
    """A motion command that ends at a position: the hub watches it to its end and says
    how it ended (arrived, stopped short, stopped by a limit switch or a STOP)."""

    argument: str = Field(description="the argument that gives the position or distance")
    relative: bool = Field(default=False, description="the argument is a distance")


class CommandDescriptor(BaseModel):
    """An action the user can trigger: ``POST /api/axes/{id}/commands``."""

    name: str
    label: str
    description: str
    group: Literal["stop", "mode", "motion", "calibration", "persist", "other"]
    arguments: list[ArgumentDescriptor] = []
    confirm: str | None = Field(
        default=None, description="text of a confirmation the UI must show before sending"
    )
    abort_command: str | None = Field(
        default=None, description="command that aborts this one while it runs"
    )
    marks_operated: bool = True
    powers_motor: bool = Field(
        default=False,
        description="the command may power a motor that is off or set it moving (SLAP2 "
        "Stop and hold sends pm): in the stop group it still needs 'move' and the "
        "control lock; every other stop (STOP, power off, halt) is open to every role",
    )
    hold_to_run: bool = Field(
        default=False,
        description="sent only by a hold-to-run control (the jog buttons, whose release "
        "stops it): the UI offers no plain button for it",
    )
    active_flag: str | None = Field(
        default=None,
        description="a flag that is on while the mode this command selects is active "
        "(the UI shows the button as engaged)",
    )
    stores_parameters: Literal["axis", "link"] | None = Field(
        default=None,
        description="the device's save command: it stores the persisted parameters of "
        "this axis (axis) or of every axis of the link (link) in non-volatile memory; "
        "the UI marks a parameter saved only while its value is the one stored",
    )
    target: MoveTarget | None = Field(
        default=None,
        description="a move to a position: its answer says it was sent, a move_outcome "
        "message says how it ended",
    )


class StopEffect(BaseModel):
    """What the device's STOP (the ``stop`` command, the top bar's STOP and Esc) does.

    A motion engineer must know before pressing it whether the motor keeps its torque:
    a vertical axis whose motor goes unpowered drops. STOP brings the axis to rest in
    the shortest distance the device allows while its position loop works, then to the
    device's safe state; where the loop is not working (``servotune.hub.loopcheck``) it cuts
    the motor's power at once (category 0) instead (docs/control.md).
    """

    summary: str = Field(description="one line for next to the STOP button: what STOP does now")
    motor_powered: bool = Field(
        description="the motor keeps holding torque after a STOP with a working loop "
        "(False: a vertical or loaded axis can drop or be back-driven)"
    )
    sends: str = Field(description="what goes to the wire")
    category: Literal[0, 1, 2] = Field(
        default=0,
        description="IEC 60204-1 stop category of STOP with a working loop: 0 power cut "
        "at once, 1 controlled stop then power off, 2 controlled stop, power kept (holds)",
    )
    loop_failed: str = Field(
        default="",
        description="one line: what STOP does instead when the loop is not working "
        "(following error growing, oscillation, current limit held)",
    )
    power_off_command: str | None = Field(
        default=None,
        description="the stop-group command that cuts the motor's power at once "
        "(category 0), open to everyone who may STOP",
    )
    gentler: list[str] = Field(
        default=[],
        description="commands of this descriptor that stop more gently (e.g. stop and "
        "hold), in the order the UI offers them",
    )


class LoopSignals(BaseModel):
    """Where to see whether an axis' position loop works: the data the hub's loop
    check (``servotune.hub.loopcheck``) reads, after a STOP, a bench run or an auto-tune
    step. Every name refers to a channel or flag of the same descriptor."""

    position_channel: str
    following_error_channel: str = Field(
        description="setpoint minus position, counts (a loop that works keeps it small "
        "against the setpoint's own motion)"
    )
    reference_channel: str | None = Field(
        default=None,
        description="what the loop is asked to follow, counts (a setpoint or a target): "
        "an error that swings while the reference goes back and forth is the loop "
        "following it, not an oscillation (None: position + following error)",
    )
    moving_flags: list[str] = Field(
        default=[],
        description="flags on while the reference moves (a profile, velocity mode); with "
        "none of them on the loop holds a fixed position",
    )
    current_limit_flag: str | None = Field(
        default=None, description="on while the drive limits the motor current"
    )
    closed_loop_flags: list[str] = Field(
        default=[],
        description="the position loop runs only while one of these flags is on (empty: "
        "always); without it the following error says nothing about the loop",
    )
    oscillation_counts: float = Field(
        gt=0,
        description="a swing of the following error this big (peak to peak) counts as "
        "one half cycle of an oscillation",
    )
    rest_velocity: float = Field(
        gt=0, description="counts/s below which the axis counts as at rest"
    )


class JogPress(BaseModel):
    """One jog direction: the descriptor command (and its arguments) a press sends."""

    command: str
    args: dict[str, int] = {}


class JogDescriptor(BaseModel):
    """Hold-to-run jog both ways, with the device's own way of reversing: a press sends
    ``minus`` or ``plus``, a release (and losing the page) sends ``release``, a
    controlled stop that keeps holding."""

    minus: JogPress
    plus: JogPress
    release: str
    title: str = Field(description="tooltip: what a press and a release do")


class ParameterConstraint(BaseModel):
    """A check across parameters: ``lower <= upper``, enforced on every write against
    the values written merged with the device's current values (422 naming the
    parameter written)."""

    lower: str = Field(description="parameter that must not exceed 'upper'")
    upper: str
    message: str = Field(description="why, in words a user can act on")


class ConsoleRule(BaseModel):
    """What the console lines whose command word is one of ``words`` do.

    The permission table checks a console line as the command it is: a read needs only
    the console, a parameter write what a parameter write needs, a line that is a
    descriptor command what that command needs (``pg`` is ``save_eeprom``), a line
    that stores or erases settings on the device what persisting needs.
    """

    words: list[str] = Field(description="command words as the device reads them, lower case")
    effect: Literal["read", "write", "command", "persist"]
    command: str | None = Field(
        default=None, description="effect 'command': the descriptor command the line is"
    )
    parameters: list[str] = Field(
        default=[], description="effect 'write': the descriptor parameters the line sets"
    )


class UnknownConsoleLineError(ValueError):
    """A console line whose effect the descriptor does not state: it is not sent."""


class ConsoleDescriptor(BaseModel):
    help: str
    multiline_commands: list[str] = []
    examples: list[str] = []
    syntax: Literal["letters", "word", "object"] = Field(
        default="word",
        description="how the device finds a line's command word: 'letters' = the leading "
        "letters once spaces are removed, any case (SLAP2: 'P G' is 'pg'); 'word' = the "
        "first word, any case (Z1100); 'object' = the object address before '=', a line "
        "without '= value' reading it (EP7047)",
    )
    rules: list[ConsoleRule] = Field(
        default=[], description="what each command word does; a word without a rule is refused"
    )

    def rule(self, line: str) -> ConsoleRule:
        """The rule of ``line``; UnknownConsoleLineError when no rule states its effect."""
        word, assigns = _console_word(self.syntax, line)
        for rule in self.rules:
            if word in rule.words:
                if self.syntax == "object" and not assigns and rule.effect == "write":
                    return ConsoleRule(words=[word], effect="read")
                return rule
        shown = word or line.strip()
        raise UnknownConsoleLineError(
            f"the console cannot tell what {shown[:40]!r} does, so it is not sent "
            "(see the console's help for the commands it knows)"
        )

    def parameters_set(self, line: str) -> list[str]:
        """The parameters ``line`` writes ([] for a read, a command or an unknown line)."""
        try:
            rule = self.rule(line)
        except UnknownConsoleLineError:
            return []
        return list(rule.parameters) if rule.effect == "write" else []


def _console_word(syntax: str, line: str) -> tuple[str, bool]:
    """(the command word of ``line`` as the device reads it, whether it assigns)."""
    if syntax == "letters":
        text = "".join(line.split()).lower()
        end = 0
        while end < len(text) and "a" <= text[end] <= "z":
            end += 1
        return text[:end], False
    if syntax == "object":
        address, equals, value = line.partition("=")
        word = "".join(address.split()).lower()
        index_text, colon, sub_text = word.partition(":")
        try:
            if colon:
                word = f"0x{int(index_text, 16):04x}:{int(sub_text, 16):02x}"
        except ValueError:
            pass
        return word, bool(equals and value.strip())
    words = line.split()
    return (words[0].lower() if words else ""), False


class TwinDescriptor(BaseModel):
    """How the 3D twin (``servotune.twin``) draws one axis: data, not device code.

    Every name refers to a channel or flag of the same descriptor. A channel that is
    ``None`` (or absent from a sample) draws no ghost; a flag that is ``None`` is never
    shown. Fault-severity flags colour the axis red with their label, whatever the device.
    """

    counts_per_rev: int = Field(gt=0, description="encoder counts per shaft revolution")
    setpoint_channel: str | None = Field(
        default=None, description="profile setpoint (counts): drawn as a translucent ghost"
    )
    target_channel: str | None = Field(
        default=None, description="target of the move (counts): a second, fainter ghost"
    )
    moving_flag: str | None = Field(
        default=None, description="on while a move or velocity job runs"
    )
    in_position_flag: str | None = Field(
        default=None, description="on when the axis has settled at its target"
    )
    switch_flags: list[str] = Field(
        default=[],
        description="limit / cam / home switch inputs, negative end first: an axis with "
        "switches also gets a linear stage view (rail, carriage, switches lit red when on)",
    )
    switch_positions_counts: list[int | None] = Field(
        default=[],
        description="where each switch sits, when the device knows it (same order as "
        "switch_flags); unknown switches are drawn at the ends of the rail",
    )


class DeviceDescriptor(BaseModel):
    """Everything the UI needs to render one axis of a device family."""

    device: str
    model: str
    title: str
    summary: str
    parameters: list[ParameterDescriptor]
    channels: list[ChannelDescriptor]
    flags: list[FlagDescriptor]
    plots: list[PlotDescriptor]
    commands: list[CommandDescriptor]
    console: ConsoleDescriptor
    stop: StopEffect
    constraints: list[ParameterConstraint] = []
    write_groups: list[list[str]] = Field(
        default=[],
        description="parameters written together, in this order (e.g. Z1100 KABH then KABD: "
        "writing KABH overwrites KABD, so the UI edits both sets and writes them as one group)",
    )
    twin: TwinDescriptor | None = Field(
        default=None, description="how the 3D twin draws the axis (None: not drawn)"
    )
    loop: LoopSignals | None = Field(
        default=None,
        description="where to see whether the position loop works (None: no loop to "
        "judge, e.g. an open-loop stepper)",
    )
    jog: JogDescriptor | None = Field(default=None, description="hold-to-run jog both ways")
    autotune: bool = Field(
        default=False,
        description="the auto-tune assistant supports this device (the UI shows its panel "
        "only then)",
    )
    bench_velocity_parameter: str | None = Field(
        default=None,
        description="the parameter a velocity_step bench test sets (the test's velocity is "
        "in its unit); null: the velocity channel's unit",
    )

    def parameter(self, name: str) -> ParameterDescriptor:
        """Return the parameter called ``name``; KeyError if the device has none."""
        for parameter in self.parameters:
            if parameter.name == name:
                return parameter
        raise KeyError(name)

    def command(self, name: str) -> CommandDescriptor:
        """Return the command called ``name``; KeyError if the device has none."""
        for command in self.commands:
            if command.name == name:
                return command
        raise KeyError(name)
