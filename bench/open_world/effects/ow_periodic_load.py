"""Open-world generator: a periodic torque on the load at a free frequency (a pump's pulsation)."""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter


class OwPeriodicLoad(Effect):
    """amplitude·sin(2π f t + phase) on disk 4."""

    name = "ow_periodic_load"
    description = "periodic torque on the load at a free frequency"
    acts_on = "load"
    family = "periodic"
    parameters = (
        Parameter("amplitude", "N·m", "torque amplitude", default=None, lower=0.0, prior=(0.0, 60.0), hidden=(20.0, 60.0)),
        Parameter("frequency", "Hz", "frequency", default=None, prior=(10.0, 300.0), hidden=(20.0, 150.0)),
        Parameter("phase", "rad", "phase at t = 0", default=0.0, lower=-4.0, upper=4.0, prior=(-3.14, 3.14)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return p.amplitude * math.sin(2.0 * math.pi * p.frequency * s.t + p.phase)
