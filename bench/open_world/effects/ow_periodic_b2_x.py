"""Open-world generator: a periodic horizontal force on the motor's drive-end bearing (a neighbouring machine)."""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter


class OwPeriodicB2X(Effect):
    """amplitude·sin(2π f t + phase) on node b2 in x."""

    name = "ow_periodic_b2_x"
    description = "periodic horizontal force on bearing b2 at a free frequency"
    acts_on = "b2_x"
    family = "periodic"
    parameters = (
        Parameter("amplitude", "N", "force amplitude", default=None, lower=0.0, prior=(0.0, 30.0), hidden=(4.0, 12.0)),
        Parameter("frequency", "Hz", "frequency", default=None, prior=(10.0, 300.0), hidden=(30.0, 200.0)),
        Parameter("phase", "rad", "phase at t = 0", default=0.0, lower=-4.0, upper=4.0, prior=(-3.14, 3.14)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return p.amplitude * math.sin(2.0 * math.pi * p.frequency * s.t + p.phase)
