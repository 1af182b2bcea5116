"""A hum at a fixed frequency on the motor rotor, whatever its speed (a test effect: a neighbouring machine's)."""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter


class MotorHum(Effect):
    """amplitude·sin(2π·frequency·t) on the motor rotor."""

    name = "motor_hum"
    description = "a hum at a fixed frequency on the motor rotor: amplitude sin(2 pi frequency t) on disk 1"
    acts_on = "motor"
    parameters = (
        Parameter("amplitude", "N·m", "hum amplitude", default=None, lower=0.0, lower_inclusive=True,
                  prior=(0.0, 50.0), hidden=(5.0, 20.0)),
        Parameter("frequency", "Hz", "hum frequency", default=148.0, prior=(20.0, 400.0)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return p.amplitude * math.sin(2.0 * math.pi * p.frequency * s.t)
