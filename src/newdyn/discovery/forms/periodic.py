"""A periodic force at a free frequency, from a source the model lacks (a fan, a neighbouring machine)."""

from __future__ import annotations

import math

import numpy as np

from . import Form, Shape, amplitude_phase, unit

STEPS = 30  # frequencies tried per resolution 1/T of the record, within one resolution of a peak


class Periodic(Form):
    term = "periodic"
    description = "a periodic force at a free frequency f: amplitude·sin(2π f t + phase)"
    coefficients = ("cosine", "sine")
    phased = True

    @classmethod
    def shapes(cls, trajectory, place, peaks):
        offsets = np.arange(-STEPS, STEPS + 1) * peaks.resolution / STEPS
        return [Shape({"frequency": float(f)}, f"{f:.2f} Hz") for peak in peaks.frequencies for f in peak + offsets if f > 0]

    @classmethod
    def log_prior(cls, trajectory, peaks, n_shapes):
        """Uniform in frequency up to the Nyquist frequency, each shape standing for its step, 1/STEPS of a resolution."""
        nyquist = 0.5 / (trajectory.t[1] - trajectory.t[0])
        return math.log(peaks.resolution / STEPS / nyquist)

    @classmethod
    def basis(cls, trajectory, place, shape):
        phase = 2 * math.pi * shape.values["frequency"] * trajectory.t
        return np.stack([np.cos(phase), np.sin(phase)])

    @classmethod
    def parameters(cls, coefficients, shape, place):
        amplitude, phase = amplitude_phase(*coefficients)
        return {"amplitude": (amplitude, unit(place)), "frequency": (shape.values["frequency"], "Hz"), "phase": (phase, "rad")}

    @classmethod
    def effect_body(cls, place, shape):
        return "p.amplitude * sincos(2.0 * math.pi * p.frequency * s.t + p.phase)[0]"
