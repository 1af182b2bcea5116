"""Open-world generator: dry friction across the coupling (a rubbing guard, a seized damper element)."""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter


class OwFrictionCoupling(Effect):
    """Coulomb friction of level F on the coupling's twist rate, as F·tanh(v / v0)."""

    name = "ow_friction_coupling"
    description = "dry friction across the coupling on its twist rate"
    acts_on = "coupling"
    family = "friction"
    parameters = (
        Parameter("friction", "N·m", "friction torque level", default=None, lower=0.0, prior=(0.0, 100.0), hidden=(8.0, 30.0)),
        Parameter("v0", "rad/s", "speed over which friction builds up", default=1e-3, prior=(1e-4, 1e-2)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return p.friction * math.tanh(s.v / p.v0)
