"""A loose motor non-drive-end bearing housing, in x."""

from __future__ import annotations

from newdyn.effects import Effect, Parameter


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
        # The healthy ground spring is taken away; in contact it acts from the wall at mode·gap (with
        # no clearance always, and then exactly as the healthy one).
        healthy = rig.k_bx * (s.x + rig.beta * s.v)
        wall = rig.k_bx * ((s.x - mode * p.gap) + rig.beta * s.v)
        return healthy - (wall if (mode != 0.0) | (p.gap == 0.0) else 0.0)

    @staticmethod
    def event(s, p, rig, mode):
        x = s.x / (p.gap if p.gap > 0.0 else 1.0)  # in clearances, so that the event is located to 1e-13 of it
        crossing = abs(x) - 1.0 if mode == 0.0 else 1.0 - mode * x
        return crossing if p.gap > 0.0 else -1.0  # with no clearance there is nothing to switch

    @staticmethod
    def switch(s, p, rig, mode):
        return 0.0 if mode != 0.0 else (1.0 if s.x > 0.0 else -1.0)
