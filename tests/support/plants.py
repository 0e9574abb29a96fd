"""Plant models for loop and FRF tests."""

from __future__ import annotations

from servotune.sim.physics import DcMotorParams
from servotune.tuning.loops import MotorModel


def motor_model(p: DcMotorParams) -> MotorModel:
    return MotorModel(
        resistance_ohm=p.resistance_ohm,
        inductance_h=p.inductance_h,
        torque_constant_nm_per_a=p.torque_constant_nm_per_a,
        inertia_kg_m2=p.inertia_kg_m2,
        viscous_friction_nm_s_per_rad=p.viscous_friction_nm_s_per_rad,
        supply_v=p.supply_v,
        counts_per_rev=p.counts_per_rev,
    )
