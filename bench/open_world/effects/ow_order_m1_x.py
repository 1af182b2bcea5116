"""Open-world generator: a horizontal force on the motor rotor at a whole order of its rotation (misalignment, a rotor rub)."""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter


class OwOrderM1X(Effect):
    """amplitude·cos(n θ1 + phase) on node m1 in x, n the whole number nearest to ``order``."""

    name = "ow_order_m1_x"
    description = "horizontal force on the motor rotor at a whole order of its rotation"
    acts_on = "m1_x"
    family = "order"
    parameters = (
        Parameter("amplitude", "N", "force amplitude", default=None, lower=0.0, prior=(0.0, 20.0), hidden=(1.5, 5.0)),
        Parameter("order", "-", "order (rounded to a whole number)", default=None, prior=(1.5, 5.5), hidden=(1.5, 4.5)),
        Parameter("phase", "rad", "phase", default=0.0, lower=-4.0, upper=4.0, prior=(-3.14, 3.14)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return p.amplitude * math.cos(math.floor(p.order + 0.5) * s.theta1 + p.phase)
