"""Backlash in the coupling: a free play of ±b in which the coupling element carries no torque.

An effect the built-in library lacks, written as a user would: effects/README.md ("Worked example")
walks through it.  Only a load that reverses the coupling torque opens the free play.
"""

from __future__ import annotations

from newdyn.effects import Effect, Parameter
from newdyn.effects.contact import clearance_event, clearance_spring, clearance_switch


class CouplingBacklash(Effect):
    """The coupling element (spring kT2 and damper β·kT2) acts only in contact with a flank, from the
    flank at ±b; inside the free play the hubs 2b and 3 turn freely against each other."""

    name = "coupling_backlash"
    description = "backlash in the coupling: the element carries torque only beyond a free play of ±b"
    acts_on = "coupling"  # s.x = θ2b − θ3, the coupling's twist
    mode_name = "contact"  # 0 inside the free play, ±1 against the flank at ±b
    parameters = (
        Parameter("b", "rad", "half the free play of the coupling", default=None, lower=0.0, lower_inclusive=True,
                  prior=(0.0, 4.0e-4), hidden=(5.0e-5, 3.0e-4)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        # Replaces the healthy element's torque: against a flank it acts from the flank, in the free play not at all.
        return clearance_spring(s.x, s.v, rig.kT2, rig.beta, p.b, mode) - rig.kT2 * (s.x + rig.beta * s.v)

    @staticmethod
    def event(s, p, rig, mode):
        return clearance_event(s.x, p.b, mode)

    @staticmethod
    def switch(s, p, rig, mode):
        return clearance_switch(s.x, mode)
