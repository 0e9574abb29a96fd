"""The SLAP2 stop plant's copy (``sim.trace.TracedDevice.unpowered``): the power-off
alone run forward from the very state a command found the device in."""

from __future__ import annotations

import math
from pathlib import Path

from servotune.devices.slap2.sim.demo import stop_plant
from servotune.sim.trace import UNPOWERED_STEP_S

TICK_S = 0.0005


def test_the_copy_taken_at_a_commands_arrival_coasts_as_st_leaves_the_device(
    tmp_path: Path,
) -> None:
    plant = stop_plant(1, tmp_path)
    module = plant.device.module(1)
    module.controller.open_loop(900)  # the loaded motor spun up open-loop
    t = 0.0
    while t < 0.4:
        t += TICK_S
        plant.advance_to(t)
    plant.receive(ord("x"))  # a command typed before arming: no copy of it
    plant.receive(0x0D)
    plant.arm()
    for byte in b"st\r":
        t += TICK_S
        plant.advance_to(t)
        plant.receive(byte)
    plant.disarm()
    arrival = plant.arrival(["st"], 0.0)
    assert arrival is not None
    at, position, speed = arrival
    assert speed > 20_000  # it was turning when the command arrived
    copy = plant.unpowered(at, 200.0, 0.15, 8.0)
    assert copy is not None
    assert copy[0][1:] == (position, speed)  # the copy starts where the command found it
    # The device itself, switched off as st does at that moment, on the same time grid.
    module.controller.stop()
    counts_per_rad = module.motor.params.counts_per_rev / (2 * math.pi)
    elapsed_s = 0.0
    for _, copy_position, copy_speed in copy[1:]:
        elapsed_s += UNPOWERED_STEP_S
        plant.device.advance_to(t + elapsed_s)
        assert copy_position == float(module.motor.count)
        assert copy_speed == module.motor.speed_rad_s * counts_per_rad
    # It coasted (hundreds of counts at least) and came to rest within the 8 s.
    assert abs(copy[-1][1] - position) > 1000 and abs(copy[-1][2]) < 200
    assert plant.unpowered(at, 200.0, 0.15, 8.0) is None  # a copy runs once
    assert plant.unpowered(at - 1.0, 200.0, 0.15, 8.0) is None  # none taken then
