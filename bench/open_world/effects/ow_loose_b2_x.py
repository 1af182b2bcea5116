"""Open-world generator: a loose motor drive-end bearing housing in x (the library's loose bearing is at b1)."""

from __future__ import annotations

from newdyn.effects import Effect, Parameter
from newdyn.effects.contact import clearance_event, clearance_spring, clearance_switch


class OwLooseB2X(Effect):
    """b2's ground spring and damper in x act only beyond a clearance ±gap."""

    name = "ow_loose_b2_x"
    description = "loose motor drive-end bearing housing in x: b2's ground spring acts only beyond ±gap"
    acts_on = "b2_x"
    family = "dead_zone"
    mode_name = "contact"
    parameters = (
        Parameter("gap", "m", "clearance of the b2 housing in x", default=None, lower=0.0, lower_inclusive=True,
                  prior=(0.0, 1.0e-7), hidden=(8.0e-9, 2.0e-8)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return rig.k_bx * (s.x + rig.beta * s.v) - clearance_spring(s.x, s.v, rig.k_bx, rig.beta, p.gap, mode)

    @staticmethod
    def event(s, p, rig, mode):
        return clearance_event(s.x, p.gap, mode)

    @staticmethod
    def switch(s, p, rig, mode):
        return clearance_switch(s.x, mode)
