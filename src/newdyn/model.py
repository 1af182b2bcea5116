"""The reference rig of ``docs/rig.md``: parameters, channels, sampling and linear matrices.

Every model quantity has one name used everywhere: in config, in the kernel's flat parameter
vector, in file attributes and in the calibration.  A model instance is just a mapping from these
names to values; :mod:`newdyn.slots` completes it with the active effects' values and packs it for the
compiled kernel.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np


@dataclass(frozen=True)
class Parameter:
    name: str
    default: float
    unit: str
    description: str
    group: str  # "rig", "operating", "record" or "effect"
    lower: float = 0.0  # exclusive unless ``lower_inclusive``
    upper: float = math.inf
    lower_inclusive: bool = False
    upper_inclusive: bool = False
    integer: bool = False

    def rounded(self, value: float) -> float:
        """``value`` as this parameter takes it: the nearest whole number for an integer parameter."""
        return float(round(value)) if self.integer else float(value)

    def problem(self, value: float) -> str | None:
        """Why ``value`` is not physical for this parameter, or None when it is."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"must be a number (got {value!r})"
        if not math.isfinite(value):
            return f"must be a finite number (got {value})"
        if self.integer and value != int(value):
            return f"must be a whole number (got {value})"
        low_ok = value >= self.lower if self.lower_inclusive else value > self.lower
        high_ok = value <= self.upper if self.upper_inclusive else value < self.upper
        if not (low_ok and high_ok):
            interval = "[("[not self.lower_inclusive] + f"{self.lower:g}, {self.upper:g}" + "])"[not self.upper_inclusive]
            unit = "" if self.unit == "-" else f" {self.unit}"
            return f"must lie in {interval}{unit} (got {value:g})"
        return None


def _p(group: str, rows: list[tuple]) -> list[Parameter]:
    """Rows of (name, default, unit, description[, bounds as keyword dict])."""
    return [Parameter(r[0], float(r[1]), r[2], r[3], group, **(r[4] if len(r) > 4 else {})) for r in rows]


_NON_NEGATIVE = {"lower_inclusive": True}
_ANGLE = {"lower": -math.inf, "upper": math.inf}  # any finite angle; only its value modulo 2π matters


# Order matters: it is the layout of the kernel's parameter vector.
PARAMETERS: tuple[Parameter, ...] = tuple(
    _p(
        "rig",
        [
            ("J1", 4.0, "kg·m²", "motor rotor inertia (total, with imbalance mass)"),
            ("J2a", 0.05, "kg·m²", "motor shaft end inertia (stick-slip side a)"),
            ("J2b", 0.10, "kg·m²", "motor-side coupling hub inertia (stick-slip side b)"),
            ("J3", 0.15, "kg·m²", "load-side coupling hub inertia"),
            ("J4", 6.0, "kg·m²", "load inertia (total, with imbalance mass)"),
            ("m1", 300.0, "kg", "motor rotor node mass"),
            ("m2", 20.0, "kg", "motor-side coupling hub node mass"),
            ("m3", 20.0, "kg", "load-side coupling hub node mass"),
            ("m4", 400.0, "kg", "load node mass"),
            ("m_b", 50.0, "kg", "mass of each bearing node"),
            ("kT1", 3.0e6, "N·m/rad", "motor shaft torsional stiffness (1–2)"),
            ("kT2", 1.0e6, "N·m/rad", "coupling element torsional stiffness (2–3)"),
            ("kT3", 2.5e6, "N·m/rad", "load shaft torsional stiffness (3–4)"),
            ("k_s", 2.0e8, "N/m", "lateral shaft stiffness b1–m1, m1–b2, b3–m4, m4–b4"),
            ("k_h", 5.0e7, "N/m", "lateral hub stiffness b2–m2, m3–b3"),
            ("k_c", 1.0e7, "N/m", "lateral coupling stiffness m2–m3"),
            ("k_bx", 5.0e8, "N/m", "bearing-to-ground stiffness, horizontal x"),
            ("k_by", 6.0e8, "N/m", "bearing-to-ground stiffness, vertical y"),
            ("beta", 3.0e-5, "s", "stiffness-proportional damping: every spring k has a damper beta·k", _NON_NEGATIVE),
            ("slip", 0.02, "-", "induction-motor slip s at T0 (sets the torque slope c_m = T0/(s·Omega))", {"upper": 1.0}),
            ("u1", 4.8e-3, "kg·m", "imbalance m·e at the motor rotor (node m1, disk 1)", _NON_NEGATIVE),
            ("u4", 6.4e-3, "kg·m", "imbalance m·e at the load (node m4, disk 4)", _NON_NEGATIVE),
            ("phi1", 0.0, "rad", "angle of the imbalance u1 on disk 1, from the disk's mark", _ANGLE),
            ("phi4", 0.0, "rad", "angle of the imbalance u4 on disk 4, from the disk's mark", _ANGLE),
        ],
    )
    + _p(
        "operating",
        [
            ("speed_rpm", 1480.0, "rpm", "synchronous motor speed Omega = 2·pi·speed_rpm/60"),
            ("T0", 1613.0, "N·m", "mean motor and load torque"),
            ("load_amp", 0.3, "-", "load pulsation amplitude a", _NON_NEGATIVE),
            ("load_freq", 12.0, "Hz", "load pulsation base frequency f_l"),
            ("load_harm", 6.0, "-", "number of load harmonics H", {"lower": 1.0, "lower_inclusive": True, "integer": True}),
        ],
    )
    + _p(
        "record",
        [
            ("load_phase", 0.0, "rad", "phase of the load pulsation at t = 0: T_l = T0 [1 + a Σ sin(h (2π f_l t + φ_l)) / h]",
             _ANGLE),
        ],
    )
)

PARAMETER_NAMES: tuple[str, ...] = tuple(p.name for p in PARAMETERS)
PARAMETER_BY_NAME: Mapping[str, Parameter] = MappingProxyType({p.name: p for p in PARAMETERS})
PARAMETER_INDEX: Mapping[str, int] = MappingProxyType({n: i for i, n in enumerate(PARAMETER_NAMES)})
DEFAULTS: Mapping[str, float] = MappingProxyType({p.name: p.default for p in PARAMETERS})
RIG_PARAMETERS = tuple(p.name for p in PARAMETERS if p.group == "rig")
OPERATING_PARAMETERS = tuple(p.name for p in PARAMETERS if p.group == "operating")
# What a recording leaves open beyond its operating condition, found from its data by the diagnosis
# (newdyn.alignment): the load pulsation's phase.  Where the recording starts on the shaft's turn is the
# imbalances' angles phi1 and phi4 (rotating the whole shaft by ψ is phi1 and phi4 by ψ).
RECORD_PARAMETERS = tuple(p.name for p in PARAMETERS if p.group == "record")
ANGLE_PARAMETERS = tuple(p.name for p in PARAMETERS if p.unit == "rad")
IMBALANCE_ANGLES = tuple(n for n in ANGLE_PARAMETERS if n in RIG_PARAMETERS)  # phi1, phi4: they turn with the record's start

# The torsional bodies' angles in shaft order, as the state holds them: motor rotor, motor shaft end, motor-side
# coupling hub, load-side hub, load.
ANGLES = ("theta1", "theta2a", "theta2b", "theta3", "theta4")
# Lateral nodes in shaft order and the springs between them (same in x and y).
NODES = ("b1", "m1", "b2", "m2", "m3", "b3", "m4", "b4")
BEARING_NODES = (0, 2, 5, 7)
DISK_NODES = {"1": 1, "4": 6}  # imbalance disks 1 and 4 sit at nodes m1 and m4
LATERAL_SPRINGS = ((0, 1, "k_s"), (1, 2, "k_s"), (2, 3, "k_h"), (3, 4, "k_c"), (4, 5, "k_h"), (5, 6, "k_s"), (6, 7, "k_s"))
NODE_MASSES = ("m_b", "m1", "m_b", "m2", "m3", "m_b", "m4", "m_b")

CHANNELS: tuple[str, ...] = tuple(f"{NODES[n]}_{d}" for n in BEARING_NODES for d in "xy") + ("w1", "w4", "torque_c")
CHANNEL_UNITS = MappingProxyType({**{c: "m" for c in CHANNELS[:8]}, "w1": "rad/s", "w4": "rad/s", "torque_c": "N·m"})


def omega(values: Mapping[str, float]) -> float:
    """Synchronous speed Omega [rad/s]."""
    return 2.0 * math.pi * values["speed_rpm"] / 60.0


@dataclass(frozen=True)
class Sampling:
    """Recorded samples: ``t_k = t_first + k / fs`` for ``k = 0 … n_samples-1``; the model starts at t = 0 from
    rig.md's state (at rest laterally), or, ``steady``, from its linearized steady state there (:func:`steady_states`),
    as a recording that starts at any moment is compared."""

    fs: float = 5000.0
    t_first: float = 0.5
    n_samples: int = 5000
    steady: bool = False

    @classmethod
    def from_window(cls, fs: float, t_warm: float, t_rec: float) -> Sampling:
        return cls(fs=float(fs), t_first=float(t_warm), n_samples=round(float(t_rec) * float(fs)))

    @property
    def times(self) -> np.ndarray:
        return self.t_first + np.arange(self.n_samples) / self.fs


def linear_matrices(values: Mapping[str, float] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass, damping and stiffness matrices of the healthy rig linearized without imbalance.

    DOF order: θ1 θ2 θ3 θ4 (J2 = J2a + J2b as one body), then x at the 8 nodes, then y.
    The motor's torque slope c_m acts as a viscous damper on θ1 to ground.
    Independent of the compiled kernel, so it serves as a check on it.
    """
    v = {**DEFAULTS, **(values or {})}
    n = 20
    M = np.zeros((n, n))
    K = np.zeros((n, n))
    M[:4, :4] = np.diag([v["J1"], v["J2a"] + v["J2b"], v["J3"], v["J4"]])
    for i, k in enumerate((v["kT1"], v["kT2"], v["kT3"])):
        K[np.ix_([i, i + 1], [i, i + 1])] += k * np.array([[1.0, -1.0], [-1.0, 1.0]])
    for offset, ground in ((4, v["k_bx"]), (12, v["k_by"])):
        for node, mass in enumerate(NODE_MASSES):
            M[offset + node, offset + node] = v[mass]
        for a, b, name in LATERAL_SPRINGS:
            K[np.ix_([offset + a, offset + b], [offset + a, offset + b])] += v[name] * np.array([[1.0, -1.0], [-1.0, 1.0]])
        for node in BEARING_NODES:
            K[offset + node, offset + node] += ground
    C = v["beta"] * K
    C[0, 0] += motor_slope(v)
    return M, C, K


def motor_slope(values: Mapping[str, float]) -> float:
    """c_m = T0 / (s·Omega): the induction motor's torque drop per rad/s above synchronous speed."""
    return values["T0"] / (values["slip"] * omega(values))


def natural_frequencies(values: Mapping[str, float] | None = None, damped: bool = True) -> np.ndarray:
    """Natural frequencies [Hz] of the linearized rig, ascending, rigid-body/overdamped modes excluded.

    ``damped=True`` takes the imaginary parts of the state-space eigenvalues (with β and the motor
    slope); ``damped=False`` the undamped generalized eigenproblem K φ = ω² M φ.
    """
    M, C, K = linear_matrices(values)
    if not damped:
        from scipy.linalg import eigh

        w2 = eigh(K, M, eigvals_only=True)
        return np.sort(np.sqrt(w2[w2 > 1e-6 * w2.max()])) / (2 * np.pi)
    lam = _eigenvalues(M, C, K)
    return np.sort(lam.imag[lam.imag > 1e-9 * np.abs(lam).max()]) / (2 * np.pi)


def _eigenvalues(M: np.ndarray, C: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The state-space eigenvalues of M q'' + C q' + K q = 0."""
    n = M.shape[0]
    Minv = np.linalg.inv(M)
    return np.linalg.eigvals(np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ K, -Minv @ C]]))


SETTLING_TIMES = 5  # time constants of the slowest mode the model runs before it is compared with a recording


def settling_time(values: Mapping[str, float] | None = None) -> float:
    """How long the linearized rig takes to forget its initial state [s]: :data:`SETTLING_TIMES` time constants of its
    most slowly decaying mode (an undamped one never forgets it and is left out).  A recording is in steady state; the
    model is compared with it from then on (the reference rig: 0.48 s, after which the start-up from rig.md's state is
    below 3e-4 of a channel's std in b1, b2 and the torsional channels, 1.5e-3 in b3, b4; from the linearized steady
    state, :func:`steady_states`, below 1e-4 with each library effect but stick-slip; tests/test_physics.py).  From the
    steady state two time constants left less than 1e-3 of a channel's std at the study's condition, but a loose bearing
    and a stick-slip joint recorded at other conditions were then fitted to χ² 1.6 and 2.2 where five explain them
    (docs/validation.md)."""
    decay = -_eigenvalues(*linear_matrices(values)).real
    return SETTLING_TIMES / float(np.min(decay[decay > 1e-9 * np.max(decay)]))


def wrap_angle(angle: float) -> float:
    """``angle`` [rad] on the circle's turn [−π, π)."""
    return float((angle + math.pi) % (2 * math.pi) - math.pi)


def steady_states(values: Mapping[str, np.ndarray]) -> np.ndarray:
    """The state at t = 0 (:func:`initial_state`'s layout) of the rig's linearized steady state, one row per element of
    the arrays ``values`` (each parameter's name → its values): the pre-twist of rig.md's start, plus the response of
    the healthy rig linearized about its speed Ω (:func:`linear_matrices`, J2a and J2b one body) to each load harmonic
    on disk 4 and to the imbalances' forces u Ω² at Ω on nodes m1 and m4, at the angles θ + φ of their disks' mean
    angles; the rotation's own angle is rig.md's (θ4 = 0 on average).  What the linearization leaves out (the
    imbalances' coupling of lateral and torsional motion, an effect's force) starts as a transient that dies out with
    the rig's modes."""
    v = {name: np.atleast_1d(np.asarray(values[name], dtype=float)) for name in PARAMETER_NAMES}
    n = max(a.size for a in v.values())
    v = {name: np.broadcast_to(a, (n,)) for name, a in v.items()}
    speed = 2.0 * math.pi * v["speed_rpm"] / 60.0
    twist3 = v["T0"] / v["kT3"]
    twist2 = twist3 + v["T0"] / v["kT2"]
    twist1 = twist2 + v["T0"] / v["kT1"]
    state = np.zeros((n, 42))
    state[:, 0:5] = np.stack([twist1, twist2, twist2, twist3, np.zeros(n)], 1)
    state[:, 21:26] = speed[:, None]

    # Torsion (θ1, θ2 = θ2a = θ2b, θ3, θ4), every load harmonic h at once: −T0 a sin(h x)/h on disk 4.
    harmonics = np.arange(1, int(np.max(v["load_harm"])) + 1)
    mass, stiffness = _chain(np.stack([v["J1"], v["J2a"] + v["J2b"], v["J3"], v["J4"]], 1), np.stack([v["kT1"], v["kT2"], v["kT3"]], 1))
    damping = v["beta"][:, None, None] * stiffness
    damping[:, 0, 0] += v["T0"] / (v["slip"] * speed)
    force = np.zeros((n, harmonics.size, 4), dtype=complex)
    amplitude = np.where(harmonics <= v["load_harm"][:, None], (v["T0"] * v["load_amp"])[:, None] / harmonics, 0.0)
    force[:, :, 3] = 1j * amplitude * np.exp(1j * harmonics * v["load_phase"][:, None])
    angles = _steady_response(mass[:, None], stiffness[:, None], damping[:, None], 2.0 * math.pi * v["load_freq"][:, None] * harmonics,
                              force)
    state[:, 0:5] += angles[0][:, :, [0, 1, 1, 2, 3]].sum(axis=1)
    state[:, 21:26] += angles[1][:, :, [0, 1, 1, 2, 3]].sum(axis=1)
    # Lateral, x and y at once: each imbalance's force u Ω² (cos, sin)(Ωt + θ̄ + φ) at its node, θ̄ its disk's pre-twist.
    springs = np.stack([v[name] for _, _, name in LATERAL_SPRINGS], 1)
    mass, stiffness = _chain(np.stack([v[name] for name in NODE_MASSES], 1), springs)
    stiffness = np.repeat(stiffness[:, None], 2, axis=1)  # (n, direction, 8, 8)
    for node in BEARING_NODES:
        stiffness[:, 0, node, node] += v["k_bx"]
        stiffness[:, 1, node, node] += v["k_by"]
    force = np.zeros((n, 2, 8), dtype=complex)
    for disk, mean_angle in (("1", twist1), ("4", 0.0)):
        whirl = v[f"u{disk}"] * speed**2 * np.exp(1j * (mean_angle + v[f"phi{disk}"]))
        force[:, :, DISK_NODES[disk]] = whirl[:, None] * np.array([1.0, -1j])  # cos = Re e^{iΩt}, sin = Re −i e^{iΩt}
    moved = _steady_response(mass[:, None], stiffness, v["beta"][:, None, None, None] * stiffness,
                             np.repeat(speed[:, None], 2, axis=1), force)
    for direction, offset in enumerate((5, 13)):
        state[:, offset:offset + 8] = moved[0][:, direction]
        state[:, 21 + offset:21 + offset + 8] = moved[1][:, direction]
    return state


def _chain(masses: np.ndarray, springs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mass and stiffness matrices (n, m, m) of chains of ``masses`` (n, m) joined by ``springs`` (n, m − 1)."""
    n, m = masses.shape
    mass = np.zeros((n, m, m))
    mass[:, range(m), range(m)] = masses
    stiffness = np.zeros((n, m, m))
    for i in range(m - 1):
        stiffness[:, i, i] += springs[:, i]
        stiffness[:, i + 1, i + 1] += springs[:, i]
        stiffness[:, i, i + 1] -= springs[:, i]
        stiffness[:, i + 1, i] -= springs[:, i]
    return mass, stiffness


def _steady_response(mass, stiffness, damping, frequency, force) -> tuple[np.ndarray, np.ndarray]:
    """Displacements and velocities at t = 0 of M q'' + C q' + K q = Re(F e^{iωt}) in steady state, for matrices (…, d, d),
    ``frequency`` ω (…) and ``force`` F (…, d)."""
    w = frequency[..., None, None]
    amplitude = np.linalg.solve(stiffness - w**2 * mass + 1j * w * damping, force[..., None])[..., 0]
    return amplitude.real, (1j * frequency[..., None] * amplitude).real


def initial_state(values: Mapping[str, float]) -> np.ndarray:
    """State at t = 0 (rig.md): speeds Omega, θ4 = 0, shafts pre-twisted by T0, lateral at rest.

    Layout (42): positions θ1 θ2a θ2b θ3 θ4, x[8], y[8]; then the same velocities.
    """
    q = np.zeros(42)
    theta3 = values["T0"] / values["kT3"]
    theta2 = theta3 + values["T0"] / values["kT2"]
    q[0:5] = (theta2 + values["T0"] / values["kT1"], theta2, theta2, theta3, 0.0)
    q[21:26] = omega(values)
    return q
