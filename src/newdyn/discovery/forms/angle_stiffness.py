"""An element's stiffness modulated by a disk's angle: a crack that breathes, an eccentric hub, a keyway."""

from __future__ import annotations

import numpy as np

from . import ELEMENT_STIFFNESS, Form, Shape, amplitude_phase
from .order import DISKS

ORDERS = (1, 2)


class AngleStiffness(Form):
    term = "angle_stiffness"
    description = "an element's stiffness modulated by disk d's angle: k (1 + depth·sin(n θ_d + phase))"
    coefficients = ("cosine", "sine")
    phased = True

    @classmethod
    def places(cls):
        return ("motor_shaft", "coupling", "load_shaft")

    @classmethod
    def shapes(cls, trajectory, place, peaks):
        return [Shape({"disk": float(d), "order": float(n)}, f"{n}x disk {d}") for d in DISKS for n in ORDERS]

    @classmethod
    def basis(cls, trajectory, place, shape):
        force = trajectory.values[ELEMENT_STIFFNESS[place]] * trajectory.x[place]
        angle = shape.values["order"] * trajectory.theta[str(int(shape.values["disk"]))]
        return np.stack([force * np.cos(angle), force * np.sin(angle)])

    @classmethod
    def parameters(cls, coefficients, shape, place):
        depth, phase = amplitude_phase(*coefficients)
        return {"depth": (depth, "-"), "order": (shape.values["order"], "-"), "phase": (phase, "rad")}

    @classmethod
    def effect_body(cls, place, shape):
        disk = str(int(shape.values["disk"]))
        return f"p.depth * rig.{ELEMENT_STIFFNESS[place]} * s.x * sincos(p.order * s.theta{disk} + p.phase)[0]"
