"""A torque ripple of the motor (a test effect)."""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter


class TorqueRipple(Effect):
    """amplitude·sin(order·θ1) on the motor rotor."""

    name = "torque_ripple"
    description = "torque ripple of the motor: amplitude sin(order θ1) on disk 1"
    acts_on = "motor"
    parameters = (
        Parameter("amplitude", "N·m", "ripple amplitude", default=None, lower=0.0, lower_inclusive=True,
                  prior=(0.0, 50.0), hidden=(5.0, 20.0)),
        Parameter("order", "-", "ripple periods per revolution", default=6.0, prior=(1.0, 12.0)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return p.amplitude * math.sin(p.order * s.theta1)
