"""Open-world generator: a torque across the motor shaft at a whole order of the motor's rotation (a keyway, a bent shaft)."""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter


class OwOrderMotorShaft(Effect):
    """amplitude·sin(n θ1 + phase) across kT1, n the whole number nearest to ``order``."""

    name = "ow_order_motor_shaft"
    description = "torque across the motor shaft at a whole order of the motor's rotation"
    acts_on = "motor_shaft"
    family = "order"
    parameters = (
        Parameter("amplitude", "N·m", "torque amplitude", default=None, lower=0.0, prior=(0.0, 100.0), hidden=(20.0, 60.0)),
        Parameter("order", "-", "order (rounded to a whole number)", default=None, prior=(0.5, 8.5), hidden=(1.5, 6.5)),
        Parameter("phase", "rad", "phase", default=0.0, lower=-4.0, upper=4.0, prior=(-3.14, 3.14)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return p.amplitude * math.sin(math.floor(p.order + 0.5) * s.theta1 + p.phase)
