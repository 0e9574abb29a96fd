"""What the UI renders for a fake servo axis: data, no page of its own."""

from __future__ import annotations

from servotune.descriptor import (
    ArgumentDescriptor,
    ChannelDescriptor,
    CommandDescriptor,
    ConsoleDescriptor,
    ConsoleRule,
    DeviceDescriptor,
    FlagDescriptor,
    ParameterDescriptor,
    PlotDescriptor,
    StopEffect,
)

from . import NAME
from .codec import DEFAULT_SPEED, POSITION_LIMIT, SPEED_RANGE


def fake_descriptor() -> DeviceDescriptor:
    return DeviceDescriptor(
        device=NAME,
        model="FS-1",
        title="Fake servo (test)",
        summary="A fake position servo on a line protocol of its own (tests/device/fake).",
        parameters=[
            ParameterDescriptor(
                name="speed",
                label="Speed",
                unit="counts/s",
                minimum=SPEED_RANGE[0],
                maximum=SPEED_RANGE[1],
                default=DEFAULT_SPEED,
                group="Motion",
                description="How fast a move runs.",
                set_command="V{value}",
                read_command="Q",
            )
        ],
        channels=[
            ChannelDescriptor(
                name="position", label="Position", unit="counts", description="Shaft position."
            )
        ],
        flags=[FlagDescriptor(name="moving", label="Moving", description="A move runs.")],
        plots=[
            PlotDescriptor(name="position", label="Position", unit="counts", series=["position"])
        ],
        commands=[
            CommandDescriptor(
                name="stop",
                label="STOP",
                description="Stop where the shaft is and hold there.",
                group="stop",
            ),
            CommandDescriptor(
                name="move_absolute",
                label="Move to",
                description="Move to an absolute position at the set speed.",
                group="motion",
                arguments=[
                    ArgumentDescriptor(
                        name="position",
                        label="Position",
                        unit="counts",
                        minimum=-POSITION_LIMIT,
                        maximum=POSITION_LIMIT,
                        required=True,
                    )
                ],
            ),
        ],
        console=ConsoleDescriptor(
            help="R position, Q speed, V<counts/s> set the speed, M<counts> move, S stop",
            examples=["R", "Q"],
            syntax="letters",
            rules=[
                ConsoleRule(words=["r", "q"], effect="read"),
                ConsoleRule(words=["v"], effect="write", parameters=["speed"]),
                ConsoleRule(words=["m"], effect="command", command="move_absolute"),
                ConsoleRule(words=["s"], effect="command", command="stop"),
            ],
        ),
        stop=StopEffect(
            summary="STOP: the shaft stops where it is and is held there",
            motor_powered=True,
            sends="S",
            category=2,
        ),
    )
