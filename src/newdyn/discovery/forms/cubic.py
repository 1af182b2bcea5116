"""Cubic stiffening (or softening) at a place: an element or a support that hardens with deflection."""

from __future__ import annotations

from . import Form, Shape, coordinate_unit, oscillating_places, resisting, unit


class Cubic(Form):
    term = "cubic"
    description = "a cubic spring k3·x³ at the place, resisting (k3 > 0 hardens, < 0 softens)"
    coefficients = ("k3",)

    @classmethod
    def places(cls):
        return oscillating_places()

    @classmethod
    def shapes(cls, trajectory, place, peaks):
        return [Shape({}, "x³")]

    @classmethod
    def basis(cls, trajectory, place, shape):
        sign = -1.0 if resisting(place) else 1.0
        return (sign * trajectory.x[place] ** 3)[None]

    @classmethod
    def parameters(cls, coefficients, shape, place):
        return {"k3": (float(coefficients[0]), f"{unit(place)}/{coordinate_unit(place)}³")}

    @classmethod
    def effect_body(cls, place, shape):
        return f"{resisting(place)}p.k3 * s.x * s.x * s.x"
