"""CNC Designer Z1100's registry entry: how its link specs read, how its link is built,
how its simulator is served and what the demo runs (builders import their modules when
called, see ``devices/slap2/entry.py``)."""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import AsyncIterator, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Final

from servotune.config import LinkRules, LinkSpec
from servotune.devices.z1100 import NAME
from servotune.devices.z1100.codec import DEFAULT_BAUD
from servotune.link.base import DriverSink, Link
from servotune.registry import (
    DemoArgs,
    DeviceEntry,
    PollSet,
    SimArgs,
    SimulatorEntry,
    StopAxis,
    StopCase,
    StopRig,
    StopRigArgs,
)

if TYPE_CHECKING:
    from servotune.autotune.context import TuningContext
    from servotune.autotune.service import DeviceTuner
    from servotune.tuning.law import DeviceLaw

# One chip, three motors: there is nothing to address.
AXES: Final = (0, 1, 2)


def build_link(spec: LinkSpec, sink: DriverSink) -> Link:
    from servotune.devices.z1100.link import Z1100Link, Z1100LinkConfig
    from servotune.transports.serial import SerialConnector

    config = Z1100LinkConfig(
        link_id=spec.link_id,
        path=spec.path,
        baud=spec.baud,
        lines=spec.lines,
        names=dict(spec.names),
    )
    return Z1100Link(config, SerialConnector(spec.path, spec.baud), sink)


def serve(args: SimArgs) -> int:
    from servotune.devices.z1100.sim.demo import serve_z1100

    serve_z1100(args.baud or DEFAULT_BAUD, args.state_dir, args.link)
    return 0


@contextlib.contextmanager
def demo_line(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """One simulated Z1100 chip with three differently loaded motors."""
    from servotune.devices.z1100.sim.demo import DEMO_NAMES, demo_chip_process

    with demo_chip_process(state_dir) as simulator:
        yield [
            LinkSpec(
                device=NAME,
                path=simulator.ready["path"],
                link_id="demo-z1100",
                baud=DEFAULT_BAUD,
                addresses=list(AXES),
                lines=512,
                names=dict(DEMO_NAMES),
            )
        ]


def poll_set(link: Link) -> PollSet:
    """The poll set of the chip: every transaction is one host/device turn."""
    from servotune.devices.z1100.link import Z1100Link

    assert isinstance(link, Z1100Link)
    config = link.config
    return PollSet(
        f"Z1100 {config.baud} baud, 3 axes, poll set GetEncoder+GetError per axis "
        f"(+GetStart, GetStop, GetSwitch every {config.status_every}th cycle), "
        "13 bytes per transaction",
        # GetEncoder + GetError of three motors, three status reads every status_every
        6.0 + 3.0 / config.status_every,
    )


def demo(args: DemoArgs) -> contextlib.AbstractContextManager[list[LinkSpec]]:
    return demo_line(args.state_dir)


@contextlib.asynccontextmanager
async def stop_rig(args: StopRigArgs) -> AsyncIterator[StopRig]:
    """The demo's chip without home switches in a process of its own, tracing the
    motor of ``args.axis`` (``<link>-x|y|z``, as the link names them)."""
    from servotune.devices.z1100.sim.demo import stop_plant
    from servotune.sim.trace import traced_serial_process

    address = "xyz".index(args.axis.rsplit("-", 1)[1])
    build = functools.partial(stop_plant, address, args.data_dir)
    async with traced_serial_process("stops-z1100", build, DEFAULT_BAUD) as (path, remote):
        spec = LinkSpec(NAME, path, args.link_id, DEFAULT_BAUD, list(AXES), 512)
        link = functools.partial(build_link, spec)
        yield StopRig(
            link,
            remote.trace,
            remote.powered,
            remote.reached,
            remote.arm,
            remote.disarm,
            remote.unpowered,
        )


# A slow sampling time stretches the chip's derivative window: with the unloaded
# motor's K at its maximum the loop settles into a limit cycle (docs/z1100-simulator.md).
STOP_OSCILLATING_GAINS: Final = {"stm": 16} | {
    f"{s}_{g}": v for s in ("kabh", "kabd") for g, v in (("k", 255), ("a", 64), ("b", 8))
}


async def _top_speed(axis: StopAxis) -> None:
    """The demo's gains, constant velocity at the flash's Vmax."""
    await axis.command("constant_velocity", {"direction": 1})
    await asyncio.sleep(1.0)


async def _limit_cycle(gains: Mapping[str, int], axis: StopAxis) -> None:
    """``gains`` written, then a move of 20 000 counts, whose limit cycle settles in."""
    await axis.write_params(dict(gains))
    position = axis.channel("position") or 0
    await axis.command("go_to_target", {"target": int(position) + 20000})
    await asyncio.sleep(1.5)


STOP_CASES: Final = (
    StopCase("x-top-speed", "x", "Z1100 X unloaded", "top speed", {}, "Vmax 100 000", _top_speed),
    StopCase("y-top-speed", "y", "Z1100 Y 5x load", "top speed", {}, "Vmax 100 000", _top_speed),
    StopCase("z-top-speed", "z", "Z1100 Z 20x load", "top speed", {}, "Vmax 100 000", _top_speed),
    StopCase(
        "x-limit-cycle",
        "x",
        "Z1100 X unloaded",
        "limit cycle",
        STOP_OSCILLATING_GAINS,
        "±600",
        functools.partial(_limit_cycle, STOP_OSCILLATING_GAINS),
    ),
)


def load_law() -> DeviceLaw:
    from servotune.devices.z1100.law import Z1100Law

    return Z1100Law()


def build_tuner(ctx: TuningContext) -> DeviceTuner:
    from servotune.devices.z1100.tuner import Z1100Tuner

    return Z1100Tuner(ctx)


ENTRY: Final = DeviceEntry(
    name=NAME,
    title="CNC Designer Z1100",
    link_rules=LinkRules(
        default_baud=DEFAULT_BAUD,
        addressing="fixed",
        fixed_addresses=AXES,
        # addresses= is ignored (the chip's axes are fixed); it is still accepted in
        # 0..15, as link specs always took it, so configs that list it keep loading.
        address_range=(0, 15),
        example="z1100:/dev/ttyUSB0",
    ),
    build_link=build_link,
    simulator=SimulatorEntry(
        serve=serve,
        demo=demo,
        pty=True,
        poll_set=poll_set,
        stop_rig=stop_rig,
        stop_cases=STOP_CASES,
    ),
    law=load_law,
    tuner=build_tuner,
    compute_modules=("servotune.devices.z1100.gain_rule",),
)
