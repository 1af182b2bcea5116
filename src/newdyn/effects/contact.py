"""A two-sided contact with a clearance: an element that acts only against a wall at ±gap (a dead zone).

Shared by effects of that shape (``loose_bearing``: b1's ground spring in a loose housing; ``coupling_backlash`` of
effects/README.md's worked example: the coupling element in a free play).  The mode is 0 free inside the clearance
and ±1 against the wall at ±gap.
"""

from __future__ import annotations

from .base import kernel_function


@kernel_function
def clearance_spring(x, v, k, beta, gap, mode):
    """The force of a spring k with damper beta·k acting from the wall at mode·gap, nothing inside the
    clearance; with no clearance always, and then exactly as the plain spring."""
    return k * ((x - mode * gap) + beta * v) if (mode != 0.0) | (gap == 0.0) else 0.0


@kernel_function
def clearance_event(x, gap, mode):
    """Positive where x leaves the clearance (free) or comes off the wall (in contact); in units of
    the clearance, so that events are located to 1e-13 of it.  With no clearance nothing switches."""
    u = x / (gap if gap > 0.0 else 1.0)
    crossing = abs(u) - 1.0 if mode == 0.0 else 1.0 - mode * u
    return crossing if gap > 0.0 else -1.0


@kernel_function
def clearance_switch(x, mode):
    """The new mode at a clearance event: free off the wall, else against the wall on x's side."""
    return 0.0 if mode != 0.0 else (1.0 if x > 0.0 else -1.0)
