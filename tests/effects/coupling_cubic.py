"""A cubic stiffening of the coupling element of one fixed size, whatever the load (a test effect)."""

from __future__ import annotations

from newdyn.effects import Effect, Parameter


class CouplingCubic(Effect):
    """k3·δ³ across the coupling, δ its twist."""

    name = "coupling_cubic"
    description = "cubic stiffening of the coupling element: k3 δ³ across it"
    acts_on = "coupling"
    parameters = (
        Parameter("k3", "N·m/rad³", "cubic stiffness", default=None, lower=0.0, lower_inclusive=True,
                  prior=(0.0, 1e11), hidden=(1e10, 3e10)),
    )

    @staticmethod
    def force(s, p, rig, mode):
        return p.k3 * s.x * s.x * s.x
