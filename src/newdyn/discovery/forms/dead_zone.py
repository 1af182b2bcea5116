"""A dead zone (backlash, a loose seat): an element or a bearing's ground spring that carries nothing inside ±b."""

from __future__ import annotations

import numpy as np

from . import ELEMENT_STIFFNESS, Form, Shape, coordinate_unit, resisting

# Clearances tried, as quantiles of |x| along the motion: down to a few per cent of its swing (a seat barely loose)
QUANTILES = np.concatenate([[0.025, 0.05], np.linspace(0.1, 0.9, 9)])


class DeadZone(Form):
    term = "dead_zone"
    description = "a dead zone of ±b: a share of the element's (ground spring's) stiffness k acts only beyond ±b"
    coefficients = ("share",)

    @classmethod
    def places(cls):
        return tuple(p for p in ELEMENT_STIFFNESS)

    @classmethod
    def shapes(cls, trajectory, place, peaks):
        x = trajectory.x[place]
        if not x.min() < 0.0 < x.max():  # never crosses zero: a free play about zero never opens
            return []
        return [Shape({"clearance": float(b)}, f"b {b:.3g}") for b in np.quantile(np.abs(x), QUANTILES)]

    @classmethod
    def basis(cls, trajectory, place, shape):
        # The stiffness taken away inside ±b: the element's force less k·clip(x, −b, b).
        k = trajectory.values[ELEMENT_STIFFNESS[place]]
        sign = 1.0 if resisting(place) else -1.0
        b = shape.values["clearance"]
        return (sign * k * np.clip(trajectory.x[place], -b, b))[None]

    @classmethod
    def parameters(cls, coefficients, shape, place):
        return {"share": (float(coefficients[0]), "-"), "clearance": (shape.values["clearance"], coordinate_unit(place))}

    @classmethod
    def effect_body(cls, place, shape):
        sign = "" if resisting(place) else "-"
        return f"{sign}p.share * rig.{ELEMENT_STIFFNESS[place]} * min(max(s.x, -p.clearance), p.clearance)"
