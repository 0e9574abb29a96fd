"""gräbner SLAP2's registry entry: how its link specs read, how its link is built,
how its simulator is served and what the demo runs.

Builders import their modules when called: the registry is read by every command
(``servotune --help`` included), which must not load every device's link for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import AsyncIterator, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Final

from servotune.config import LinkRules, LinkSpec
from servotune.devices.slap2 import NAME
from servotune.devices.slap2.codec import DEFAULT_BAUD, MAX_ADDRESS
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


def build_link(spec: LinkSpec, sink: DriverSink) -> Link:
    from servotune.devices.slap2.link import Slap2Link, Slap2LinkConfig
    from servotune.transports.serial import SerialConnector

    config = Slap2LinkConfig(
        link_id=spec.link_id,
        path=spec.path,
        addresses=list(spec.addresses),
        baud=spec.baud,
        lines=spec.lines,
        names=dict(spec.names),
    )
    return Slap2Link(config, SerialConnector(spec.path, spec.baud), sink)


def serve(args: SimArgs) -> int:
    from servotune.devices.slap2.sim.demo import serve_slap2

    serve_slap2(list(args.addresses), args.baud or DEFAULT_BAUD, args.state_dir, args.link)
    return 0


@contextlib.contextmanager
def demo_line(state_dir: Path) -> Iterator[list[LinkSpec]]:
    """Two SLAP2 modules (addresses 0 and 1) sharing one simulated RS232 line."""
    from servotune.devices.slap2.sim.demo import DEMO_ADDRESSES, DEMO_NAMES, demo_line_process

    with demo_line_process(state_dir) as simulator:
        yield [
            LinkSpec(
                device=NAME,
                path=simulator.ready["path"],
                link_id="demo-slap2",
                baud=DEFAULT_BAUD,
                addresses=list(DEMO_ADDRESSES),
                lines=512,
                names=dict(DEMO_NAMES),
            )
        ]


def poll_set(link: Link) -> PollSet:
    """The poll set of a SLAP2 line: every character the host sends waits for its echo
    (the reply follows the CR's echo without a turn), for every module on the line."""
    from servotune.devices.slap2.link import Slap2Link

    assert isinstance(link, Slap2Link)
    config = link.config
    turns = float(sum(len(m) + 1 for m in config.poll_commands))
    if config.rve_every:
        turns += 4 / config.rve_every
    modules = len(config.addresses)
    if modules > 1:
        turns += len("se0") + 1
    return PollSet(
        f"SLAP2 {config.baud} baud, {modules} module(s) on one line, poll set "
        f"{'+'.join(config.poll_commands)} (+rve every {config.rve_every}th cycle)",
        turns * modules,
    )


def demo(args: DemoArgs) -> contextlib.AbstractContextManager[list[LinkSpec]]:
    return demo_line(args.state_dir)


@contextlib.asynccontextmanager
async def stop_rig(args: StopRigArgs) -> AsyncIterator[StopRig]:
    """The demo's line without limit switches in a process of its own, tracing the
    module of ``args.axis`` (``<link>-<address>``)."""
    from servotune.devices.slap2.sim.demo import DEMO_ADDRESSES, stop_plant
    from servotune.sim.trace import traced_serial_process

    address = int(args.axis.rsplit("-", 1)[1])
    build = functools.partial(stop_plant, address, args.data_dir)
    async with traced_serial_process("stops-slap2", build, DEFAULT_BAUD) as (path, remote):
        spec = LinkSpec(NAME, path, args.link_id, DEFAULT_BAUD, list(DEMO_ADDRESSES), 512)
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


STOP_TOP_SV: Final = 20000  # the sv slider's end: 187 000 counts/s (5 500 rpm)
STOP_GOOD_GAINS: Final = {"kp": 600, "ki": 10, "kd": 1500}  # stable on both modules
STOP_FACTORY_GAINS: Final = {"kp": 40, "ki": 40, "kd": 80}
STOP_OSCILLATING_GAINS: Final = {"kp": 2000, "ki": 0, "kd": 0}


async def _top_speed(gains: Mapping[str, int], axis: StopAxis) -> None:
    """Unpowered, ``gains`` written, then velocity mode at the sv slider's end."""
    await axis.command("power_off", {})
    await axis.write_params(dict(gains))
    await axis.write_params({"velocity": STOP_TOP_SV, "acceleration": 65535})
    await axis.command("velocity_mode", {})
    # Long enough for the loop check to see the loop work (hub.loopcheck.EVIDENCE_S).
    await asyncio.sleep(1.2)


async def _limit_cycle(gains: Mapping[str, int], axis: StopAxis) -> None:
    """Unpowered, ``gains`` written, then a 2000-count position step, whose limit cycle
    settles in."""
    await axis.command("power_off", {})
    await axis.write_params(dict(gains))
    await axis.write_params({"velocity": 65535, "acceleration": 65535})
    await axis.command("position_mode", {})
    await axis.command("move_relative", {"distance": 2000})
    await asyncio.sleep(1.5)


def _case(name: str, address: int, gains: Mapping[str, int], speed: str) -> StopCase:
    label = ("SLAP2 #0 unloaded", "SLAP2 #1 with load")[address]
    if "limit-cycle" in name:
        setup = functools.partial(_limit_cycle, gains)
        return StopCase(name, str(address), label, "limit cycle", gains, speed, setup)
    setup = functools.partial(_top_speed, gains)
    return StopCase(name, str(address), label, "top speed", gains, speed, setup)


STOP_CASES: Final = (
    _case("unloaded-top-speed", 0, STOP_FACTORY_GAINS, "vm sv 20000"),
    _case("unloaded-limit-cycle", 0, STOP_OSCILLATING_GAINS, "±190"),
    _case("loaded-top-speed", 1, STOP_GOOD_GAINS, "vm sv 20000"),
    _case("loaded-top-speed-factory", 1, STOP_FACTORY_GAINS, "vm sv 20000"),
    _case("loaded-limit-cycle", 1, STOP_FACTORY_GAINS, "±1900 @ step"),
)


def load_law() -> DeviceLaw:
    from servotune.devices.slap2.law import Slap2Law

    return Slap2Law()


def build_tuner(ctx: TuningContext) -> DeviceTuner:
    from servotune.devices.slap2.tuner import Slap2Tuner

    return Slap2Tuner(ctx)


ENTRY: Final = DeviceEntry(
    name=NAME,
    title="gräbner SLAP2",
    link_rules=LinkRules(
        default_baud=DEFAULT_BAUD,
        addressing="modules",
        address_range=(0, MAX_ADDRESS),
        example="slap2:/dev/ttyUSB0?addresses=0,1",
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
    compute_modules=("servotune.devices.slap2.gain_rule",),
)
