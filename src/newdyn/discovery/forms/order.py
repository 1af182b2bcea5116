"""A force at an order of a disk's rotation: a ripple or an imbalance-like force that turns with the shaft."""

from __future__ import annotations

import math

import numpy as np

from . import Form, Shape, amplitude_phase, mean_speed_hz, unit

DISKS = ("1", "4")
MAX_ORDER = 24


class Order(Form):
    term = "order"
    description = "a force at a whole order n of disk d's rotation: amplitude·sin(n θ_d + phase)"
    coefficients = ("cosine", "sine")
    phased = True

    @classmethod
    def shapes(cls, trajectory, place, peaks):
        shapes = []
        for disk in DISKS:
            speed = mean_speed_hz(trajectory, disk)
            # A whole order within the record's resolution of a peak.
            orders = {round(peak / speed) for peak in peaks.frequencies if abs(peak - speed * round(peak / speed)) <= peaks.resolution}
            shapes += [Shape({"disk": float(disk), "order": float(n)}, f"{n}x disk {disk}") for n in sorted(orders) if 1 <= n <= MAX_ORDER]
        return shapes

    @classmethod
    def log_prior(cls, trajectory, peaks, n_shapes):
        """Uniform over the disks and their orders 1 … MAX_ORDER."""
        return -math.log(len(DISKS) * MAX_ORDER)

    @classmethod
    def basis(cls, trajectory, place, shape):
        angle = shape.values["order"] * trajectory.theta[str(int(shape.values["disk"]))]
        return np.stack([np.cos(angle), np.sin(angle)])

    @classmethod
    def parameters(cls, coefficients, shape, place):
        amplitude, phase = amplitude_phase(*coefficients)
        return {"amplitude": (amplitude, unit(place)), "order": (shape.values["order"], "-"), "phase": (phase, "rad")}

    @classmethod
    def effect_body(cls, place, shape):
        disk = str(int(shape.values["disk"]))
        return f"p.amplitude * sincos(p.order * s.theta{disk} + p.phase)[0]"
