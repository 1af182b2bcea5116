"""Coulomb friction on a relative speed: a rub, a dry contact in a joint."""

from __future__ import annotations

import numpy as np

from . import Form, Shape, coordinate_unit, oscillating_places, resisting, unit

SMOOTHING = 0.01  # the speed below which friction grows linearly, as a share of the speed's standard deviation


class Friction(Form):
    term = "friction"
    description = "Coulomb friction of level F on the place's rate v, smoothed below v_s: F v / sqrt(v² + v_s²), resisting"
    coefficients = ("friction",)

    @classmethod
    def places(cls):
        return oscillating_places()

    @classmethod
    def shapes(cls, trajectory, place, peaks):
        v_s = SMOOTHING * float(np.std(trajectory.v[place]))
        return [Shape({"v_smooth": v_s}, f"v_s {v_s:.3g}")] if v_s > 0 else []

    @classmethod
    def basis(cls, trajectory, place, shape):
        v = trajectory.v[place]
        sign = -1.0 if resisting(place) else 1.0
        return (sign * v / np.sqrt(v * v + shape.values["v_smooth"] ** 2))[None]

    @classmethod
    def parameters(cls, coefficients, shape, place):
        return {"friction": (float(coefficients[0]), unit(place)), "v_smooth": (shape.values["v_smooth"], f"{coordinate_unit(place)}/s")}

    @classmethod
    def effect_body(cls, place, shape):
        return f"{resisting(place)}p.friction * s.v / math.sqrt(s.v * s.v + p.v_smooth * p.v_smooth)"
