"""Candidate forms of a missing term: one file each, behind the one interface of :class:`Form`.

A form is a parametric physical term (a periodic force, a ripple at an order of a disk's rotation,
friction on a relative speed, ...) at a place of the rig.  Written as f(t) = Σ_i c_i φ_i(t; shape),
it is linear in its coefficients c given its *shape* (a frequency, an order, a clearance), which
discovery scans over values read from the data.  The basis φ_i is evaluated along the calibrated
model's motion (:class:`Trajectory`): for a force that depends on the state this is the first-order
(Born) approximation, which ranks forms; the best one is then fitted on the full simulator.

Each form also writes itself out as an effect file (:meth:`Form.effect_body`) with named parameters
and units, so that a discovered term joins the library as any user's effect.
"""

from __future__ import annotations

import importlib
import math
import pkgutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ... import model, simulation
from ...effects import PLACES
from ...effects.base import ELEMENT_PLACES, TORSIONAL, TORSIONAL_BODIES, TORSIONAL_PLACES

#: Where a place's coordinate is in the simulator's state: (a, b) with x = a − b (b None: x = a).
_COORDINATES: Mapping[str, tuple[str, str | None]] = {
    **TORSIONAL_BODIES, **{f"{node}_{axis}": (f"{axis}_{node}", None) for node in model.NODES for axis in "xy"},
}
#: The stiffness of the element at an across-element place, or of a bearing node's ground spring.
ELEMENT_STIFFNESS: Mapping[str, str] = {
    **{place: torsional.stiffness for place, torsional in TORSIONAL.items() if torsional.stiffness is not None},
    **{f"{model.NODES[node]}_{axis}": f"k_b{axis}" for node in model.BEARING_NODES for axis in "xy"},
}
#: Places a force can be estimated at: all but the slip joint, whose locked halves move as one.
ESTIMABLE_PLACES: tuple[str, ...] = tuple(p for p in PLACES if p != "slip_joint")


def unit(place: str) -> str:
    """The unit of a force at ``place``."""
    return "N·m" if place in TORSIONAL_PLACES else "N"


def coordinate_unit(place: str) -> str:
    """The unit of ``place``'s coordinate."""
    return "rad" if place in TORSIONAL_PLACES else "m"


@dataclass(frozen=True)
class Trajectory:
    """The calibrated model's motion on the simulation grid t = k/fs from t = 0: each place's coordinate
    and rate, and the two imbalance disks' angles."""

    t: np.ndarray
    x: Mapping[str, np.ndarray]
    v: Mapping[str, np.ndarray]
    theta: Mapping[str, np.ndarray]  # "1", "4"
    values: Mapping[str, float]  # the model values it was simulated with

    @classmethod
    def simulate(cls, values: Mapping[str, float], fs: float, n_samples: int, max_step: float, steady: bool = False) -> Trajectory:
        states = sorted({name for pair in _COORDINATES.values() for name in pair if name})
        outputs = states + [f"d{name}" for name in states]
        run = dict(zip(outputs, simulation.simulate(values, model.Sampling(fs, 0.0, n_samples, steady), outputs, max_step)))

        def coordinate(place, prefix):
            a, b = _COORDINATES[place]
            return run[prefix + a] - (run[prefix + b] if b else 0.0)

        return cls(np.arange(n_samples) / fs, {p: coordinate(p, "") for p in PLACES}, {p: coordinate(p, "d") for p in PLACES},
                   {"1": run["theta1"], "4": run["theta4"]}, dict(values))


@dataclass(frozen=True)
class Peaks:
    """Lines in the residual: their frequencies [Hz], strongest first, and the record's resolution 1/T [Hz]
    within which each is known."""

    frequencies: tuple[float, ...]
    resolution: float


@dataclass(frozen=True)
class Shape:
    """One value of a form's nonlinear parameters, with what it is called and its unit."""

    values: Mapping[str, float]  # e.g. {"frequency": 72.4}
    label: str  # e.g. "72.4 Hz"


class Form:
    """Base class of a candidate form; subclass it once per file (see the package docstring)."""

    term: ClassVar[str]  # a short name, e.g. "periodic"
    description: ClassVar[str]  # what it is, in one line
    coefficients: ClassVar[tuple[str, ...]]  # names of c_i, e.g. ("cosine", "sine")
    # Coefficients that are a phasor of time or of a disk's angle, whose origin is each record's own (separate records
    # share no clock nor angle mark): scored over several records, each record gets its own.
    phased: ClassVar[bool] = False

    @classmethod
    def places(cls) -> Sequence[str]:
        """The places it can act on (default: every place a force can be estimated at)."""
        return ESTIMABLE_PLACES

    @classmethod
    def shapes(cls, trajectory: Trajectory, place: str, peaks: Peaks) -> list[Shape]:
        """The shapes to try, from the motion and the residual's spectral ``peaks``."""
        raise NotImplementedError

    @classmethod
    def basis(cls, trajectory: Trajectory, place: str, shape: Shape) -> np.ndarray:
        """φ_i(t) on the trajectory's grid: (coefficient, time), in the place's force unit per unit c_i."""
        raise NotImplementedError

    @classmethod
    def parameters(cls, coefficients: np.ndarray, shape: Shape, place: str) -> dict[str, tuple[float, str]]:
        """The term's named physical parameters (value, unit) from the coefficients and the shape."""
        raise NotImplementedError

    @classmethod
    def log_prior(cls, trajectory: Trajectory, peaks: Peaks, n_shapes: int) -> float:
        """The prior probability of one shape (default: uniform over the ``n_shapes`` tried)."""
        return -math.log(n_shapes)

    @classmethod
    def effect_body(cls, place: str, shape: Shape) -> str:
        """The effect file's force expression (Python, reading ``s``, ``p``, ``rig``, ``math`` and ``sincos``),
        its parameters named as in :meth:`parameters`; a disk the shape turns with is written into it."""
        raise NotImplementedError

    @classmethod
    def frequency_hz(cls, shape: Shape, trajectory: Trajectory) -> float | None:
        """The term's frequency [Hz]: its own, or its order of its disk's mean speed; None if it has neither."""
        if "frequency" in shape.values:
            return shape.values["frequency"]
        if "order" in shape.values:
            return shape.values["order"] * mean_speed_hz(trajectory, str(int(shape.values["disk"])))
        return None

    @classmethod
    def order(cls, shape: Shape) -> float | None:
        return shape.values.get("order")


def resisting(place: str) -> str:
    """The sign, in an effect's force at ``place``, of a force that resists a positive coordinate: across an
    element its force acts like the element's own torque (+), on a disk or node it pushes it (−)."""
    return "" if place in ELEMENT_PLACES else "-"


def oscillating_places() -> tuple[str, ...]:
    """Places whose coordinate oscillates about zero rather than growing with the rotation (not the disks)."""
    return tuple(p for p in ESTIMABLE_PLACES if p not in ("motor", "load"))


def amplitude_phase(cosine: float, sine: float) -> tuple[float, float]:
    """c·cos φ + s·sin φ = A sin(φ + ψ): (A, ψ) with ψ in (−π, π]."""
    return math.hypot(cosine, sine), math.atan2(cosine, sine)


def mean_speed_hz(trajectory: Trajectory, disk: str) -> float:
    """A disk's mean rotation frequency over the trajectory [Hz]."""
    theta = trajectory.theta[disk]
    return float((theta[-1] - theta[0]) / (trajectory.t[-1] - trajectory.t[0]) / (2 * math.pi))


def _discover() -> dict[str, type[Form]]:
    found = {}
    for info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{info.name}")
        for obj in vars(module).values():
            if isinstance(obj, type) and issubclass(obj, Form) and obj is not Form and obj.__module__ == module.__name__:
                found[obj.term] = obj
    return dict(sorted(found.items()))


#: The catalogue: every Form subclass in this package, by term.
FORMS: Mapping[str, type[Form]] = _discover()
