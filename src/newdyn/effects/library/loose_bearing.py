"""A loose motor non-drive-end bearing housing, in x."""

from __future__ import annotations

from newdyn.effects import Effect, Parameter
from newdyn.effects.contact import clearance_event, clearance_spring, clearance_switch


class LooseBearing(Effect):
    """b1's ground spring and damper in x act only beyond a clearance ±gap (a dead zone): in
    contact with the wall at ±gap they push from it, inside the clearance nothing holds b1."""

    name = "loose_bearing"
    description = "loose motor non-drive-end bearing housing in x: b1's ground spring and damper act only beyond ±gap"
    acts_on = "b1_x"
    mode_name = "contact"  # 0 free inside the clearance; ±1 in contact with the wall at ±gap
    # Blind-test range (default rig, 40 dB; residual as in stick_slip.py): b1_x off by 2.2 σ, residual
    # 0.66 (k_bx −2 %) at 2e-9; 35 at 2e-8.
    parameters = (
        Parameter("gap", "m", "clearance g of the b1 housing in x", default=None, lower=0.0, lower_inclusive=True,
                  prior=(0.0, 1.0e-7), hidden=(2.0e-9, 2.0e-8)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        # The healthy ground spring is taken away and acts from the wall instead.
        return rig.k_bx * (s.x + rig.beta * s.v) - clearance_spring(s.x, s.v, rig.k_bx, rig.beta, p.gap, mode)

    @staticmethod
    def event(s, p, rig, mode):
        return clearance_event(s.x, p.gap, mode)

    @staticmethod
    def switch(s, p, rig, mode):
        return clearance_switch(s.x, mode)
