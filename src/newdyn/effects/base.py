"""The interface every physical effect implements: one class in one file.

An effect is something the healthy rig of ``docs/rig.md`` does not contain: a friction joint,
a crack, a loose bearing, a torque ripple.  It declares what it is (name, one-line description), its
named parameters (units, physical bounds, default, the prior range a diagnosis fits over and the
range a blind test draws from), *where* it acts (one of :data:`PLACES`) and *what* it adds there:

``force(s, p, rig, mode)``
    the generalized force the effect adds at its place (N·m on a torsional place, N on a lateral
    one; sign convention in :data:`PLACES`), as a function of the kinematics ``s``
    (:class:`Kinematics`), its own parameters ``p`` (attributes named as its :class:`Parameter` s),
    the rig's parameter values ``rig`` (attributes named as in :mod:`newdyn.model`, plus ``Omega``)
    and its mode.

An effect that switches (a joint that sticks and slips, a contact that opens and closes) has one
*mode* variable, a number that is 0 at t = 0, and two more functions:

``event(s, p, rig, mode)``
    negative while the current mode holds; the simulator locates the time where it turns positive;
``switch(s, p, rig, mode)``
    the new mode at that event.  Right after a switch the new mode's event function is evaluated
    again, so a joint that re-sticks and cannot hold its torque slips again at once.

An effect on the ``slip_joint`` with ``locks_joint = True`` keeps the joint locked (2a and 2b move
as one body) while its mode is 0; when the joint locks, both sides take their momentum-weighted
common speed.

These three functions are compiled into the batched simulation kernel (numba) and called as plain
Python by the independent SciPy reference, so they must be plain arithmetic on numbers: ``math``
functions, conditional expressions, ``min``/``max``/``abs``, and helpers decorated with
:func:`kernel_function` (such as :func:`sincos`, a sine and cosine that keeps the kernel's lanes
vectorized).  They must not return NaN for any admissible state and parameters.

Everything else an effect may declare is plain Python, run once per simulation: :meth:`Effect.rig_values`
(rig values the effect sets, e.g. where a joint splits an inertia), :meth:`Effect.problems`
(admissibility beyond each parameter's bounds) and :meth:`Effect.admissible` (the nearest admissible
values, used while fitting).
"""

from __future__ import annotations

import functools
import math
from collections import namedtuple
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .. import model


@dataclass(frozen=True)
class TorsionalPlace:
    """A torsional place: across the element between bodies ``a`` and ``b`` (s.x = θa − θb), or on disk ``a`` alone
    (``b`` None, s.x = θa), the bodies named by their angles in :data:`newdyn.model.ANGLES`; ``stiffness`` is the rig
    parameter of the element's spring, where it is one."""

    description: str
    a: str
    b: str | None = None
    stiffness: str | None = None


#: Places an effect can act on -> what its coordinate ``s.x`` is and how its force acts, each written once here.
#: Across an element between bodies a and b (a on the motor side), ``s.x`` is θa − θb and the
#: effect's force τ acts like the element's own spring torque k·x: −τ on a, +τ on b.
#: On a disk, ``s.x`` is its angle and the force is a torque on it (+: speeding it up).
#: On a lateral node direction, ``s.x`` is its displacement and the force acts on it (+: along +x/+y).
TORSIONAL: Mapping[str, TorsionalPlace] = {
    "motor": TorsionalPlace("disk 1 (motor rotor): a torque on it; s.x = θ1", "theta1"),
    "motor_shaft": TorsionalPlace("across the motor shaft kT1 (1 – 2a): s.x = θ1 − θ2a", "theta1", "theta2a", "kT1"),
    "slip_joint": TorsionalPlace("across the joint between motor shaft end 2a and motor-side hub 2b: s.x = θ2a − θ2b",
                                 "theta2a", "theta2b"),
    "coupling": TorsionalPlace("across the coupling element kT2 (2b – 3): s.x = θ2b − θ3", "theta2b", "theta3", "kT2"),
    "load_shaft": TorsionalPlace("across the load shaft kT3 (3 – 4): s.x = θ3 − θ4", "theta3", "theta4", "kT3"),
    "load": TorsionalPlace("disk 4 (load): a torque on it; s.x = θ4", "theta4"),
}
TORSIONAL_PLACES: Mapping[str, str] = {place: torsional.description for place, torsional in TORSIONAL.items()}
#: The bodies each torsional place lies across, (a, b) with s.x = θa − θb, or (a, None) on disk a with s.x = θa.
TORSIONAL_BODIES: Mapping[str, tuple[str, str | None]] = {place: (torsional.a, torsional.b) for place, torsional in TORSIONAL.items()}
#: Places across an element between two bodies (an effect's force there acts like the element's torque).
ELEMENT_PLACES: tuple[str, ...] = tuple(place for place, torsional in TORSIONAL.items() if torsional.b is not None)
LATERAL_PLACES: Mapping[str, str] = {
    f"{node}_{axis}": f"node {node} in {axis}: a force on it; s.x = its displacement" for node in model.NODES for axis in "xy"
}
PLACES: Mapping[str, str] = {**TORSIONAL_PLACES, **LATERAL_PLACES}

#: What an effect's functions see of the rig's motion: its place's coordinate and rate, time, the
#: angles and speeds of the two imbalance disks, and the torque the slip joint carries while locked
#: (the paper's T_f, Eq. 3b; computed in every mode).
Kinematics = namedtuple("Kinematics", "t x v theta1 theta4 omega1 omega4 joint_torque")
#: The rig's values an effect's functions see: every model parameter, and the synchronous speed Omega.
RIG_FIELDS: tuple[str, ...] = (*model.PARAMETER_NAMES, "Omega")
RigValues = namedtuple("RigValues", RIG_FIELDS)

_FUNCTION_OPTIONS = {"cache": True, "error_model": "numpy", "inline": "always"}


class KernelFunction:
    """A helper of effects' functions: plain Python where Python calls it (the effect files' checks, the SciPy
    reference), numba's compiled function once a kernel is built from them (:func:`kernel_ready`).  Compiling
    waits until then, so that reading effect files — as the Snakefile's parse does — does not import numba."""

    def __init__(self, function: Callable):
        functools.update_wrapper(self, function)
        self.py_func = function
        self._compiled = None

    def __call__(self, *args):
        return self.py_func(*args)

    def compiled(self) -> Callable:
        if self._compiled is None:
            from numba import njit

            self._compiled = njit(**_FUNCTION_OPTIONS)(self.py_func)
            kernel_ready(self.py_func)  # after: the module's globals hold this one too
        return self._compiled


def kernel_function(function: Callable) -> KernelFunction:
    """Make a helper callable from an effect's functions, in the kernel and in plain Python alike."""
    return KernelFunction(function)


def kernel_ready(function: Callable) -> Callable:
    """``function``, its module's kernel functions swapped for their compiled versions: numba resolves the names a
    function calls through its module's globals when it compiles it."""
    names = function.__globals__
    for name, value in list(names.items()):
        if isinstance(value, KernelFunction):
            names[name] = value.compiled()
    return function


# --- sin and cos that vectorize -------------------------------------------------------------------
# Cody-Waite reduction by π/2 and the fdlibm (musl) kernels.  Error ≤ 1 ulp, ≤ 1.2e-16 absolute, for
# |x| < 1e6 (k·_PIO2_HI stays exact); libm's result differs by one ulp in ~3 % of arguments.
_INV_PIO2 = 6.36619772367581382433e-01
_PIO2_HI = 1.57079632673412561417e00  # first 33 bits of π/2
_PIO2_LO = 6.07710050650619224932e-11  # π/2 - _PIO2_HI
_ROUNDER = 6755399441055744.0  # 1.5·2^52: (x + R) - R rounds x to the nearest integer
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11


@kernel_function
def sincos(x):
    """(sin x, cos x) without calls or branches, so the kernel's lane loops stay vectorized
    (``math.sin`` and ``math.cos`` are correct too, but turn them scalar)."""
    k = (x * _INV_PIO2 + _ROUNDER) - _ROUNDER  # nearest integer to x / (π/2)
    r = x - k * _PIO2_HI  # exact
    tail = k * _PIO2_LO
    hi = r - tail  # reduced argument hi + lo, |hi| ≤ π/4
    lo = (r - hi) - tail
    z = hi * hi
    zz = z * z
    v = z * hi
    rs = _S2 + z * (_S3 + z * _S4) + z * zz * (_S5 + z * _S6)
    sin_r = hi - ((z * (0.5 * lo - v * rs) - lo) - v * _S1)
    rc = z * (_C1 + z * (_C2 + z * _C3)) + zz * zz * (_C4 + z * (_C5 + z * _C6))
    half_z = 0.5 * z
    one_minus = 1.0 - half_z
    cos_r = one_minus + (((1.0 - one_minus) - half_z) + (z * rc - hi * lo))
    quadrant = k - 4.0 * (((k * 0.25 - 0.375) + _ROUNDER) - _ROUNDER)  # k mod 4 (floor by rounding)
    odd = (quadrant == 1.0) | (quadrant == 3.0)
    s = cos_r if odd else sin_r
    c = sin_r if odd else cos_r
    s = -s if quadrant >= 2.0 else s
    c = -c if (quadrant == 1.0) | (quadrant == 2.0) else c
    return s, c


def shaft_angle(name: str, description: str) -> Parameter:
    """A parameter for where on a shaft an effect sits [rad], for an effect whose force depends on a shaft's angle (the
    disks' angles ``s.theta1``, ``s.theta4`` are those of their marks): nobody measures it, so a diagnosis fits it and
    a blind test draws it over the whole turn; 0 is the mark."""
    return Parameter(name, "rad", description, default=0.0, prior=(-math.pi, math.pi), lower=-2 * math.pi, upper=2 * math.pi,
                     lower_inclusive=True, upper_inclusive=True, on_shaft=True)


@dataclass(frozen=True)
class Parameter:
    """A named effect parameter: unit, physical bounds, default, and its diagnosis and blind-test ranges.

    ``default`` is a number or a function of the rig's values (a dict).  ``prior`` is the uniform range
    a diagnosis fits over; ``hidden`` the range a blind test draws from (default: ``prior``), chosen
    so that every draw is visible above the noise.  ``sets_rig`` parameters do not enter the force
    functions: they set rig values through :meth:`Effect.rig_values`.  ``on_shaft`` marks an angle on a shaft
    (:func:`shaft_angle`): where a record starts turns it as it turns the imbalances' angles.
    """

    name: str
    unit: str
    description: str
    default: float | Callable[[Mapping[str, float]], float]
    prior: tuple[float, float]
    hidden: tuple[float, float] | None = None
    lower: float = 0.0  # exclusive unless lower_inclusive
    upper: float = math.inf
    lower_inclusive: bool = False
    upper_inclusive: bool = False
    sets_rig: bool = False
    on_shaft: bool = False

    def bounds(self) -> model.Parameter:
        """The physical bounds as a :class:`newdyn.model.Parameter`, which says why a value is not physical."""
        return model.Parameter(self.name, math.nan, self.unit, self.description, "effect", self.lower, self.upper,
                               self.lower_inclusive, self.upper_inclusive)

    def problem(self, value) -> str | None:
        return self.bounds().problem(value)

    def default_value(self, rig: Mapping[str, float]) -> float:
        return float(self.default(rig) if callable(self.default) else self.default)

    @property
    def draw_range(self) -> tuple[float, float]:
        return self.hidden if self.hidden is not None else self.prior


class Effect:
    """Base class of a physical effect; subclass it once per file (see the module docstring)."""

    name: ClassVar[str]
    description: ClassVar[str]
    acts_on: ClassVar[str]
    parameters: ClassVar[tuple[Parameter, ...]]
    mode_name: ClassVar[str | None] = None  # the mode variable's name in outputs; None: no switching
    locks_joint: ClassVar[bool] = False  # slip_joint only: the joint is locked while the mode is 0
    source: ClassVar[str] = ""  # the file it was read from (set by the registry)
    content_hash: ClassVar[str] = ""  # SHA-256 of that file's content (set by the registry)

    force: ClassVar[Callable]
    event: ClassVar[Callable | None] = None
    switch: ClassVar[Callable | None] = None

    # --- plain-Python declarations -------------------------------------------------------------------
    @classmethod
    def rig_values(cls, values: Mapping[str, float], rig: Mapping[str, float]) -> dict[str, float]:
        """Rig parameter values the effect sets from its ``sets_rig`` parameters (default: none)."""
        return {}

    @classmethod
    def problems(cls, values: Mapping[str, float], rig: Mapping[str, float]) -> list[tuple[str, str]]:
        """(parameter, problem) for combinations of otherwise physical values that are not admissible."""
        return []

    @classmethod
    def admissible(cls, values: dict[str, np.ndarray], rig: Mapping[str, float]) -> dict[str, np.ndarray]:
        """The nearest admissible values to rows of ``values`` (arrays by parameter name); a fit's
        optimizer and sampler may propose any point of the prior box."""
        return values

    # --- derived ------------------------------------------------------------------------------------
    @classmethod
    def switching(cls) -> bool:
        return cls.mode_name is not None

    @classmethod
    def parameter_names(cls) -> tuple[str, ...]:
        return tuple(p.name for p in cls.parameters)

    @classmethod
    def shaft_angles(cls) -> tuple[str, ...]:
        """Its parameters that are angles on a shaft (:func:`shaft_angle`)."""
        return tuple(p.name for p in cls.parameters if p.on_shaft)

    @classmethod
    def kernel_parameters(cls) -> tuple[Parameter, ...]:
        """The parameters its force, event and switch functions read (``p``), in declaration order."""
        return tuple(p for p in cls.parameters if not p.sets_rig)

    @classmethod
    def parameter(cls, name: str) -> Parameter:
        return next(p for p in cls.parameters if p.name == name)

    @classmethod
    def defaults(cls, rig: Mapping[str, float]) -> dict[str, float]:
        return {p.name: p.default_value(rig) for p in cls.parameters}
