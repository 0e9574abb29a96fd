"""Auto-tune test material: plant models, move specs, limits, request helpers."""

from __future__ import annotations

import math
from typing import Any

from servotune.devices.slap2.codec import ACCELERATION_MAX, VELOCITY_MAX
from servotune.devices.slap2.law import MoveSpec
from servotune.devices.z1100.law import (
    Kab,
    MoveProfile,
)
from servotune.sim.physics import DcMotorParams
from servotune.tuning.plants import PlantModel, Z1100Plant

# SLAP2: a position step, and the auto-tune limits of the SLAP2 tests.
STEP = MoveSpec(1000, VELOCITY_MAX, ACCELERATION_MAX, latency_s=0.01)


LIMITS = {"max_pwm": 80, "max_distance_counts": 8000, "response": "no_overshoot"}


def plant_model(params: DcMotorParams) -> PlantModel:
    """The first-order model that physics.py's motor reduces to (electrical pole ~80 us
    neglected): PWM -> counts/s gain, mechanical time constant, friction as PWM."""
    kt, r = params.torque_constant_nm_per_a, params.resistance_ohm
    b = params.viscous_friction_nm_s_per_rad
    volts_per_pwm = params.supply_v / 255
    counts_per_rad = params.counts_per_rev / (2 * math.pi)
    return PlantModel(
        gain=kt / (kt * kt + b * r) * volts_per_pwm * counts_per_rad,
        tau_s=params.inertia_kg_m2 * r / (kt * kt + b * r),
        friction_pwm=params.coulomb_friction_nm * r / kt / volts_per_pwm,
    )


# Z1100: gains that move but leave room to tune, and the move the tests time.
MEDIOCRE = Kab(8, 16, 8)


PROFILE = MoveProfile(10_000, 100_000, 1_000_000)


def physics_plant(load_kg_m2: float) -> Z1100Plant:
    """The first-order model physics.py's motor reduces to (electrical pole neglected)."""
    p = DcMotorParams(load_inertia_kg_m2=load_kg_m2)
    kt, r, b = p.torque_constant_nm_per_a, p.resistance_ohm, p.viscous_friction_nm_s_per_rad
    counts_per_rad = p.counts_per_rev / (2 * math.pi)
    return Z1100Plant(
        kt / (kt * kt + b * r) * p.supply_v * counts_per_rad,
        p.inertia_kg_m2 * r / (kt * kt + b * r),
    )


def again(response: Any) -> bool:
    """Whether a failed identification (a test's precondition) is worth one more try,
    as a user would: the link lost the starved pty simulator mid-staircase ("no module
    answers": the link's supervision, devices/slap2/link.py), or the product said the
    measurement could not support a model (409 ``kind: measurement``, e.g. no gains
    meet the rule on a model fitted from a stalled record). Anything else fails."""
    if response.status_code == 200:
        return False
    text = response.text
    return "no module answers" in text or (
        response.status_code == 409 and response.json().get("kind") == "measurement"
    )
